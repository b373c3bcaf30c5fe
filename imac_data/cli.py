"""What the command-line entry points share: where outputs go, quiet libraries, exit codes.

Exit codes of every ``python -m imac_data.*`` command: 0 success; 2 bad input (a clear
message names the file, key or field); 1 only for a bug (a traceback).
"""

from __future__ import annotations

import os
from pathlib import Path

EXIT_OK, EXIT_BUG, EXIT_BAD_INPUT = 0, 1, 2

__all__ = ["default_root", "cache_home", "quiet_libraries", "EXIT_OK", "EXIT_BUG", "EXIT_BAD_INPUT"]


def default_root(repo_id: str) -> Path:
    """Where LeRobot looks for ``repo_id``: ``$HF_LEROBOT_HOME/<repo_id>``."""
    from lerobot.utils.constants import HF_LEROBOT_HOME

    return Path(HF_LEROBOT_HOME) / repo_id


def cache_home() -> Path:
    return Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "imac"


def quiet_libraries() -> None:
    """Keep the console to our progress bars: SVT-AV1 banners, libav muxer notes and
    the datasets library's per-file bars say nothing a user acts on."""
    os.environ.setdefault("SVT_LOG", "1")  # SVT-AV1: errors only
    import av
    import datasets

    av.logging.set_level(av.logging.ERROR)
    datasets.disable_progress_bars()
