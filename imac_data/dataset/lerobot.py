"""LeRobot, in one place: every LeRobot name our dataset code uses comes from here."""

from __future__ import annotations

from pathlib import Path

from lerobot.utils.constants import HF_LEROBOT_HOME

__all__ = ["default_root"]


def default_root(repo_id: str) -> Path:
    """Where LeRobot looks for ``repo_id``: ``$HF_LEROBOT_HOME/<repo_id>``."""
    return Path(HF_LEROBOT_HOME) / repo_id
