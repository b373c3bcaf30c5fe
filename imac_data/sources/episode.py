"""The one interface every source's episodes are read through.

An episode is opened as a context manager and read by frame range, so memory follows the
range, not the episode. The HDF5 reader (:class:`~imac_data.sources.hdf5.EpisodeReader`)
and the LeRobot reader (:class:`~imac_data.sources.lerobot_episodes.LeRobotEpisodeReader`)
implement it; the pipeline (:mod:`imac_data.augment.pipeline`) reads nothing else.
What a depth source sees of an episode (:class:`EpisodeViews`) and what it gives
(:class:`DepthSource`) are here too, so that the depth sources (:mod:`imac_data.sources.depth`,
:mod:`imac_data.sources.da3`) share them without importing each other.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np

from imac_data.core.cameras import Camera
from imac_data.errors import InputError

__all__ = ["EpisodeSource", "EpisodeViews", "DepthSource"]


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


@dataclass
class EpisodeViews:
    """One episode as a depth source sees it.

    ``images[cam]``: ``(T, H, W, 3)`` uint8 RGB; ``cameras[cam]``: the calibration
    at that image resolution; ``poses[cam]``: ``(T, 4, 4)`` camera-to-world
    (OpenCV); ``depth_mm[cam]``: recorded depth, ``(T, H', W')`` millimetres
    (optional; only :class:`RecordedDepth` reads it). ``name`` is used in messages.
    """

    images: Mapping[str, np.ndarray]
    cameras: Mapping[str, Camera]
    poses: Mapping[str, np.ndarray]
    depth_mm: Mapping[str, np.ndarray] = field(default_factory=dict)
    name: str = "episode"

    @property
    def num_frames(self) -> int:
        lengths = {len(v) for v in self.poses.values()} | {len(v) for v in self.images.values()}
        if len(lengths) != 1:
            raise InputError(f"{self.name}: views have different frame counts {sorted(lengths)}")
        return lengths.pop()


@runtime_checkable
class DepthSource(Protocol):
    """Anything that turns an episode's views into metric depth."""

    def depth(self, views: EpisodeViews) -> dict[str, np.ndarray]:
        """``{cam: (T, H, W) float32 metres}`` at each camera's stored resolution; 0 = invalid."""
        ...

    def describe(self) -> dict[str, Any]:
        """JSON-ready description, recorded as ``info["imac"]["depth"]["source"]``."""
        ...
