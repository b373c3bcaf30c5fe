"""A free-space estimate before a build starts: warn when the output plainly will not fit.

A build's staging directory holds, at its peak, every episode's shard and the merged
dataset (its copy of them) at once, each with the robot description once (the shards
carry none): about twice the output. The output's size is bounded below from its pixels:
the encoded streams took 0.14 bytes per pixel and frame on the 10-episode 96x128
simulated dataset and 0.22 on the 120x160 test episodes (all 15 streams together);
:data:`BYTES_PER_PIXEL` is a third of the lower one, so the warning fires only when the
output plainly will not fit, never on a close call. The build goes on after the warning
(the estimate may be wrong for unusual footage); if the disk does fill, it stops with exit
3 and the finished shards stay in staging, so a rerun with more space resumes.
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

__all__ = ["BYTES_PER_PIXEL", "STREAMS_PER_CAMERA", "estimate_build_bytes", "free_bytes", "warn_if_short_of_space"]

BYTES_PER_PIXEL = 0.05
STREAMS_PER_CAMERA = 4  # depth, motion, contact r2s, contact s2g (beside the recorded RGB)


def estimate_build_bytes(total_frames: int, image_hw: dict[str, tuple[int, int]], stream_hw: tuple[int, int],
                         description_bytes: int) -> int:
    """A lower bound of the disk a build needs at its peak (module docstring)."""
    pixels = sum(h * w for h, w in image_hw.values()) + STREAMS_PER_CAMERA * len(image_hw) * stream_hw[0] * stream_hw[1]
    return int(2 * (total_frames * pixels * BYTES_PER_PIXEL + description_bytes))


def free_bytes(path: Path) -> int:
    """Free bytes for an unprivileged writer on the file system that holds ``path`` (or
    would: its nearest existing ancestor)."""
    path = Path(path)
    while not path.exists() and path != path.parent:
        path = path.parent
    return shutil.disk_usage(path).free


def warn_if_short_of_space(root: Path, need: int) -> bool:
    """Print a warning and return True when less than ``need`` bytes are free at ``root``."""
    free = free_bytes(root)
    if free >= need:
        return False
    print(f"warning: {root} has {free / 1e6:.1f} MB free, the build needs at least about {need / 1e6:.1f} MB; "
          "it will likely stop with 'No space left on device' (exit 3). Finished episodes are kept in staging, "
          "so a rerun after freeing space resumes", file=sys.stderr)
    return True
