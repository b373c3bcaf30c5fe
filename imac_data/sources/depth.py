"""Where an episode's depth comes from: one small interface (:class:`DepthSource`), the
recorded depth, no depth, and the recipe's choice among them and Depth Anything 3.

==============  ==========================================================================
``recorded``    the source's own depth (sensor millimetres, the simulator's ground truth, a
                LeRobot depth feature), in metres
``da3``         Depth Anything 3 (:mod:`imac_data.sources.da3`): all views of a timestep posed
                together; with fewer than three cameras, its monocular metric model
``none``        no depth: the pipeline makes the motion streams only
==============  ==========================================================================

A source maps one chunk of an episode's views to ``{cam: (T, H, W) float32 metres}`` at the
stored image size (0 = invalid).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from imac_data.core.metric_depth import depth_from_millimetres, resize_depth
from imac_data.errors import InputError
from imac_data.sources.da3 import check_da3_inputs, make_da3_source, uses_monocular
from imac_data.sources.episode import DepthSource, EpisodeViews

__all__ = ["DepthSource", "EpisodeViews", "RecordedDepth", "NoDepth", "episode_views", "DepthSourceKind",
           "DEPTH_SOURCES", "depth_source_kind", "check_depth_inputs", "make_depth_source", "uses_monocular"]


def episode_views(raw, rig, *, name: str = "episode") -> EpisodeViews:
    """:class:`EpisodeViews` of a :class:`~imac_data.sources.hdf5.RawEpisode` on a
    :class:`~imac_data.core.rig.Rig`: cameras rescaled to the image size, wrist cameras posed
    by forward kinematics of the measured state."""
    missing = sorted(set(rig.names) - set(raw.images))
    if missing:
        raise InputError(f"{name}: the calibration has camera(s) {missing} that the episode has no images for")
    rig = rig.with_image_sizes({c: raw.images[c].shape[1:3] for c in rig.names})
    poses = rig.camera_poses(raw.qpos, dtype=torch.float64).numpy()
    return EpisodeViews(images={c: raw.images[c] for c in rig.names}, cameras=dict(rig.cameras),
                        poses={c: poses[:, v] for v, c in enumerate(rig.names)},
                        depth_mm={c: d for c, d in raw.depth_mm.items() if c in rig.cameras}, name=name)


# --------------------------------------------------------------------------- recorded
class RecordedDepth:
    """The episodes' own depth (``depth_mm``: sensor or simulator), in metres.

    Integer or float millimetres -> float32 metres (0 stays 0 = invalid; negative
    values raise :class:`InputError`). Depth recorded at another resolution than
    the image is resized to it with :func:`~imac_data.core.depth.resize_depth` (nearest,
    no mixing across edges); it must be registered to the colour camera.
    """

    needs_images = False  # only the recorded depth is read

    def __init__(self, cameras: Sequence[str] | None = None):
        self.cameras = list(cameras) if cameras is not None else None

    def depth(self, views: EpisodeViews) -> dict[str, np.ndarray]:
        cams = self.cameras if self.cameras is not None else sorted(views.cameras)
        out = {}
        for cam in cams:
            if cam not in views.depth_mm:
                raise InputError(
                    f"{views.name}: no recorded depth for camera {cam!r} (has {sorted(views.depth_mm)}); "
                    "record depth or use an estimator such as DepthAnything3"
                )
            mm = np.asarray(views.depth_mm[cam])
            if mm.ndim != 3:
                raise InputError(f"{views.name} camera {cam!r}: recorded depth must be (T, H, W); got {mm.shape}")
            metres = depth_from_millimetres(mm, name=f"{views.name} camera {cam!r}")
            if cam in views.cameras:
                c = views.cameras[cam]
                metres = resize_depth(metres, (c.height, c.width), name=f"{views.name} camera {cam!r}")
            out[cam] = np.ascontiguousarray(metres, dtype=np.float32)
        return out

    def describe(self) -> dict[str, Any]:
        return {"kind": "recorded", "from": "the raw episodes' depth (millimetres -> metres)"}


class NoDepth:
    """No depth: ``depth: none`` in a recipe. The pipeline writes the motion streams only
    (no depth, no contact streams, no caps); :meth:`depth` is never called."""

    needs_images = False

    def depth(self, views: EpisodeViews) -> dict[str, np.ndarray]:
        raise InputError(f"{views.name}: this build has no depth source (depth.source: none)")

    def describe(self) -> dict[str, Any]:
        return {"kind": "none", "from": "no depth: motion streams only, no depth or contact streams"}


# ----------------------------------------------------------------------------- the recipe's choice


@dataclass(frozen=True)
class DepthSourceKind:
    """A recipe's ``depth.source`` choice: how its source is made for a rig of ``num_cameras``
    cameras, ``make(section, recipe_file, num_cameras, local_files_only=...)``, and what is
    checked before any work, ``check(section, recipe_file, num_cameras) -> the model it loads``."""

    make: Callable[..., DepthSource]
    check: Callable[..., str | None] | None = None


# depth.source -> its kind. A new depth source is its module (a DepthSource) and one entry here.
DEPTH_SOURCES: dict[str, DepthSourceKind] = {
    "recorded": DepthSourceKind(make=lambda section, recipe_file, num_cameras, **_: RecordedDepth()),
    "da3": DepthSourceKind(make=make_da3_source, check=check_da3_inputs),
    "none": DepthSourceKind(make=lambda section, recipe_file, num_cameras, **_: NoDepth()),
}


def depth_source_kind(section, recipe_file: str) -> DepthSourceKind:
    """The registered kind of a recipe's ``depth.source`` (:class:`InputError` naming the field)."""
    if section.source not in DEPTH_SOURCES:
        raise InputError(f"{recipe_file or '<recipe>'}: depth.source: must be one of {list(DEPTH_SOURCES)}, got "
                         f"{section.source!r}")
    return DEPTH_SOURCES[section.source]


def check_depth_inputs(section, recipe_file: str, num_cameras: int) -> str | None:
    """Fail early on an unknown depth source or a missing input of one (a ``da3`` model
    directory that is not there); returns the model the build will load (None if none)."""
    kind = depth_source_kind(section, recipe_file)
    return kind.check(section, recipe_file, num_cameras) if kind.check is not None else None


def make_depth_source(section, recipe_file: str, num_cameras: int, *, local_files_only: bool = False):
    """The :class:`~imac_data.sources.episode.DepthSource` of a recipe's ``depth:`` section for a
    rig of ``num_cameras`` cameras."""
    return depth_source_kind(section, recipe_file).make(section, recipe_file, num_cameras,
                                                        local_files_only=local_files_only)
