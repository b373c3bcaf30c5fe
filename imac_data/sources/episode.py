"""The one interface every source's episodes are read through.

An episode is opened as a context manager and read by frame range, so memory follows the
range, not the episode. The HDF5 reader (:class:`~imac_data.sources.hdf5.EpisodeReader`)
and the LeRobot reader (:class:`~imac_data.sources.lerobot_episodes.LeRobotEpisodeReader`)
implement it; the pipeline (:mod:`imac_data.augment.pipeline`) reads nothing else.
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import numpy as np

__all__ = ["EpisodeSource"]


@runtime_checkable
class EpisodeSource(Protocol):
    """One source episode: joint vectors at once, frames by range.

    ``path``: what error messages name (a file, or a dataset and episode index);
    ``qpos``, ``action`` ``(T, D)`` float; ``qvel`` ``(T, D)`` or None; ``image_hw``:
    camera -> ``(H, W)``; ``info``: the episode's metadata
    (:class:`~imac_data.sources.hdf5.EpisodeInfo`) or None.
    """

    path: Any
    qpos: np.ndarray
    action: np.ndarray
    qvel: np.ndarray | None
    image_hw: dict[str, tuple[int, int]]

    @property
    def num_frames(self) -> int: ...

    def images(self, cam: str, start: int, stop: int) -> np.ndarray:
        """RGB frames ``start:stop`` of ``cam``: ``(n, H, W, 3)`` uint8."""
        ...

    def depth_mm(self, cam: str, start: int, stop: int) -> np.ndarray | None:
        """Recorded depth frames ``start:stop`` of ``cam`` in millimetres, or None."""
        ...

    def close(self) -> None: ...

    def __enter__(self) -> EpisodeSource: ...

    def __exit__(self, *exc) -> None: ...
