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

import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np
import torch

from imac_data.core.cameras import Camera
from imac_data.core.depth import depth_from_millimetres, resize_depth
from imac_data.errors import InputError
from imac_data.sources.da3 import (
    DEFAULT_DA3_METRIC_MODEL,
    DEFAULT_DA3_MODEL,
    DepthAnything3,
    DepthAnything3Metric,
    looks_like_hub_id,
)

__all__ = ["DepthSource", "EpisodeViews", "RecordedDepth", "NoDepth", "episode_views", "check_depth_inputs",
           "make_depth_source", "uses_monocular"]


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


@runtime_checkable
class DepthSource(Protocol):
    """Anything that turns an episode's views into metric depth."""

    def depth(self, views: EpisodeViews) -> dict[str, np.ndarray]:
        """``{cam: (T, H, W) float32 metres}`` at each camera's stored resolution; 0 = invalid."""
        ...

    def describe(self) -> dict[str, Any]:
        """JSON-ready description, recorded as ``info["imac"]["depth"]["source"]``."""
        ...


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


def uses_monocular(num_cameras: int) -> bool:
    """DA3's multi-view scale fit needs three posed views; fewer use the monocular metric model."""
    return num_cameras < 3


def _model(section, recipe_file: str, monocular: bool) -> str:
    value = section.monocular_model if monocular else section.model
    field = "depth.monocular_model" if monocular else "depth.model"
    if value is None:
        return DEFAULT_DA3_METRIC_MODEL if monocular else DEFAULT_DA3_MODEL
    path = Path(os.path.expandvars(os.path.expanduser(value)))
    if not path.is_absolute() and recipe_file:
        local = Path(recipe_file).parent / path
        if local.exists() or not looks_like_hub_id(value):
            path = local
    if path.exists():
        return str(path)
    if looks_like_hub_id(value) and not value.startswith(("/", ".")):
        return value
    raise InputError(f"{recipe_file or '<recipe>'}: {field}: the Depth Anything 3 model directory {path} does not "
                     "exist (give a directory holding config.json and model.safetensors, or a Hugging Face "
                     "model id such as depth-anything/DA3-BASE)")


def check_depth_inputs(section, recipe_file: str, num_cameras: int) -> str | None:
    """Fail early on a ``da3`` model directory that is not there; returns the model the
    build will load (None unless ``da3``)."""
    if section.source != "da3":
        return None
    return _model(section, recipe_file, uses_monocular(num_cameras))


def make_depth_source(section, recipe_file: str, num_cameras: int, *, local_files_only: bool = False):
    """The :class:`~imac_data.sources.depth.DepthSource` of a recipe's ``depth:`` section for a
    rig of ``num_cameras`` cameras."""
    if section.source == "none":
        return NoDepth()
    if section.source == "recorded":
        return RecordedDepth()
    model = _model(section, recipe_file, uses_monocular(num_cameras))
    cls = DepthAnything3Metric if uses_monocular(num_cameras) else DepthAnything3
    return cls(model, device=section.device, batch_size=section.batch_size, process_res=section.process_res,
               local_files_only=local_files_only)
