"""The model's image layout: per-view frames <-> the six-panel mosaic, and the resize.

Views side by side in view order (head, left wrist, right wrist), the RGB row over the
colour-depth row; control videos have one row per view and are duplicated vertically.
Views are resized without padding to sides the backbone can patchify, K rescaled per axis so
it stays exact; colour depth is resized nearest-pixel, so every colour is one the codec wrote
(``docs/world-model.md``, "Conventions"). Float tensors in [0, 1], ``(..., 3, H, W)``."""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from imac_data.core.cameras import rescale_intrinsics
from imac_data.errors import InputError

ROWS = 2  # RGB row over colour-depth row
MAX_ASPECT_CHANGE = 0.05  # a view size whose aspect differs more from the camera's is refused


def view_size(source_hw: tuple[int, int], height: int, width: int | None = None, *, multiple: int,
              num_views: int, field: str = "data.view_height") -> tuple[int, int]:
    """The per-view model resolution for cameras of ``source_hw``.

    ``height`` is taken as given; ``width`` (default: from the aspect ratio) is rounded to
    the nearest size that makes the mosaic width a multiple of ``multiple``. Raises
    :class:`InputError` naming ``field`` when the backbone cannot patchify the mosaic or
    when an explicit width distorts the aspect by more than 5 %.
    """
    h_step = multiple // math.gcd(ROWS, multiple)
    w_step = multiple // math.gcd(num_views, multiple)
    if height % h_step:
        lo, hi = (height // h_step) * h_step, (height // h_step + 1) * h_step
        raise InputError(f"{field}: {height} cannot be patchified: the mosaic height {ROWS} x {height} must be a "
                         f"multiple of {multiple} (the backbone's spatial compression x patch); use "
                         f"{lo or hi} or {hi}")
    aspect = source_hw[1] / source_hw[0]
    explicit_width = width
    if width is None:
        width = max(w_step, int(round(height * aspect / w_step)) * w_step)
    elif width % w_step:
        lo, hi = (width // w_step) * w_step, (width // w_step + 1) * w_step
        raise InputError(f"data.view_width: {width} cannot be patchified: the mosaic width {num_views} x {width} "
                         f"must be a multiple of {multiple}; use {lo or hi} or {hi}")
    change = abs(width / height / aspect - 1)
    if change > MAX_ASPECT_CHANGE and explicit_width is None:
        ok = [hh for hh in range(h_step, 8 * max(height, h_step) + 1, h_step)
              if abs(max(w_step, round(hh * aspect / w_step) * w_step) / hh / aspect - 1) <= MAX_ASPECT_CHANGE]
        near = sorted(ok, key=lambda hh: abs(hh - height))[:2]
        raise InputError(f"{field}: no view width near the cameras' aspect {aspect:.3g} patchifies at height {height}; "
                         f"use view_height {' or '.join(map(str, sorted(near)))} (mosaic sides must be multiples of "
                         f"{multiple}; views are resized without padding)")
    if change > MAX_ASPECT_CHANGE:
        raise InputError(f"data.view_width: {height}x{width} per view changes the cameras' aspect "
                         f"({source_hw[0]}x{source_hw[1]}) by {100 * change:.0f} % (views are resized without "
                         f"padding); leave view_width unset to keep the aspect")
    return int(height), int(width)


def rescale_K(K, from_hw: tuple[int, int], to_hw: tuple[int, int]) -> np.ndarray:
    """Intrinsics after :func:`resize_frames` from ``from_hw`` to ``to_hw`` (pixel centres
    at integer coordinates; ``imac_data.core.cameras.rescale_intrinsics``, the one K rule)."""
    return rescale_intrinsics(np.asarray(K), from_hw, to_hw)


def rescale_cameras(cameras: dict, to_hw: tuple[int, int]) -> dict:
    """``{name: Camera}`` at the model's view size (K rescaled; poses unchanged)."""
    return {name: cam.rescaled(width=to_hw[1], height=to_hw[0]) for name, cam in cameras.items()}


def resize_frames(frames: torch.Tensor, hw: tuple[int, int], *, kind: str = "rgb") -> torch.Tensor:
    """Resize ``(..., 3, H, W)`` frames to ``hw``: ``kind`` ``rgb`` (also controls) is
    antialiased bilinear, ``depth`` (colour depth) is nearest-pixel."""
    if tuple(frames.shape[-2:]) == tuple(hw):
        return frames
    lead = frames.shape[:-3]
    x = frames.reshape(-1, *frames.shape[-3:])
    if kind == "depth":
        x = F.interpolate(x, size=hw, mode="nearest-exact")
    elif kind == "rgb":
        x = F.interpolate(x.float(), size=hw, mode="bilinear", antialias=True, align_corners=False).clamp(0, 1)
    else:
        raise ValueError(f"kind must be 'rgb' or 'depth', got {kind!r}")
    return x.reshape(*lead, *x.shape[-3:])


def _row(views: torch.Tensor) -> torch.Tensor:
    """``(..., V, 3, h, w)`` -> ``(..., 3, h, V * w)``."""
    return torch.cat(views.unbind(-4), dim=-1)


def assemble(rgb: torch.Tensor, depth: torch.Tensor) -> torch.Tensor:
    """Per-view RGB and colour depth ``(..., V, 3, h, w)`` -> mosaic ``(..., 3, 2h, V*w)``."""
    if rgb.shape != depth.shape:
        raise ValueError(f"rgb {tuple(rgb.shape)} and depth {tuple(depth.shape)} views differ in shape")
    return torch.cat([_row(rgb), _row(depth)], dim=-2)


def controls(control: torch.Tensor) -> torch.Tensor:
    """A per-view control ``(..., V, 3, h, w)`` -> ``(..., 3, 2h, V*w)``, duplicated
    vertically so it lines up with both rows of the mosaic."""
    row = _row(control)
    return torch.cat([row, row], dim=-2)


def split(mosaic: torch.Tensor, num_views: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Mosaic ``(..., 3, 2h, V*w)`` -> ``(rgb, depth)`` per view, each ``(..., V, 3, h, w)``:
    the inverse of :func:`assemble` (decode the depth with the dataset's codec)."""
    H, W = mosaic.shape[-2:]
    if H % ROWS or W % num_views:
        raise ValueError(f"a {H}x{W} mosaic does not split into {ROWS} rows of {num_views} views")
    h = H // ROWS
    rows = [mosaic[..., r * h:(r + 1) * h, :] for r in range(ROWS)]
    per_view = [torch.stack(row.chunk(num_views, dim=-1), dim=-4) for row in rows]
    return per_view[0], per_view[1]


def control_views(control_mosaic: torch.Tensor, num_views: int) -> torch.Tensor:
    """The per-view control ``(..., V, 3, h, w)`` of a duplicated control mosaic (top row)."""
    return split(control_mosaic, num_views)[0]
