"""Metric depth arrays: from a sensor's millimetres, and resized to another image size (nearest pixel, or the
mean of an area's valid depths). Every function takes numpy arrays or torch tensors and returns the same kind; 0
(or NaN) is invalid depth throughout. The colour codec that stores them is :mod:`imac_data.core.depth`."""

from __future__ import annotations

import sys

import numpy as np

from imac_data.errors import InputError

__all__ = ["area_resize_depth", "depth_from_millimetres", "dtype_name", "is_torch", "resize_depth"]


def is_torch(x) -> bool:
    torch = sys.modules.get("torch")  # never import torch for numpy callers
    return torch is not None and isinstance(x, torch.Tensor)


def dtype_name(x) -> str:
    return str(x.dtype).removeprefix("torch.")


def depth_from_millimetres(depth_mm, *, name: str = "depth"):
    """Integer (e.g. uint16) or float millimetres -> float32 metres; 0 stays 0 (invalid).

    numpy in, numpy out; torch in, torch out. Negative values raise InputError.
    """
    if is_torch(depth_mm):
        torch = sys.modules["torch"]
        if depth_mm.dtype == torch.bool or depth_mm.is_complex():
            raise InputError(f"{name}: millimetre depth must be integer or float; got {dtype_name(depth_mm)}")
        metres = depth_mm.to(torch.float64 if depth_mm.dtype == torch.float64 else torch.float32) / 1000.0
    else:
        depth_mm = np.asarray(depth_mm)
        if depth_mm.dtype.kind not in "iuf":
            raise InputError(f"{name}: millimetre depth must be integer or float; got {dtype_name(depth_mm)}")
        out = np.float64 if depth_mm.dtype == np.float64 else np.float32
        metres = depth_mm.astype(out) / out(1000.0)
    negative = metres < 0
    if bool(negative.any()):
        raise InputError(
            f"{name}: {int(negative.sum())} negative millimetre value(s) (lowest "
            f"{float(metres[negative].min()) * 1000:.6g} mm); depth must be >= 0 (0 = invalid)"
        )
    return metres


def _resize_inputs(depth, size, name: str, torch_in: bool):
    """Validated ``(depth, (h, w))`` of a depth resize: at least 2-D depth, a positive size."""
    if not torch_in:
        depth = np.asarray(depth)
    if depth.ndim < 2:
        raise InputError(f"{name}: depth must be at least 2-D (..., H, W); got shape {tuple(depth.shape)}")
    try:
        h, w = (int(v) for v in size)
    except (TypeError, ValueError):
        raise InputError(f"{name}: size must be (height, width); got {size!r}") from None
    if h <= 0 or w <= 0:
        raise InputError(f"{name}: size must be positive; got {size!r}")
    return depth, (h, w)


def resize_depth(depth, size: tuple[int, int], *, name: str = "depth"):
    """Nearest-neighbour resize of depth ``(..., H, W)`` to ``size = (h, w)``; numpy in,
    numpy out; torch in, torch out (same device, any leading batch shape).

    Each output pixel takes the source pixel that contains its centre (pixel edges
    scale, the convention of :func:`imac_data.core.cameras.rescale_intrinsics`), so depths
    are never averaged across an edge (no flying pixels) and invalid pixels (0 / NaN)
    are never mixed into valid ones: a value is either copied or not used.
    """
    torch_in = is_torch(depth)
    depth, (h, w) = _resize_inputs(depth, size, name, torch_in)
    H, W = depth.shape[-2:]
    if (H, W) == (h, w):
        return depth
    ys = np.minimum(((np.arange(h) + 0.5) * (H / h)).astype(np.int64), H - 1)
    xs = np.minimum(((np.arange(w) + 0.5) * (W / w)).astype(np.int64), W - 1)
    if torch_in:
        torch = sys.modules["torch"]
        ys_t, xs_t = torch.as_tensor(ys, device=depth.device), torch.as_tensor(xs, device=depth.device)
        return depth.index_select(-2, ys_t).index_select(-1, xs_t)
    return depth[..., ys[:, None], xs[None, :]]


def _area_weights(n_out: int, n_in: int) -> np.ndarray:
    """``(n_out, n_in)``: how much of output pixel ``i``'s span (pixel edges scale) source pixel
    ``j`` covers, in source pixels."""
    edges = np.arange(n_out + 1) * (n_in / n_out)
    j = np.arange(n_in)[None]
    return np.clip(np.minimum(edges[1:, None], j + 1) - np.maximum(edges[:-1, None], j), 0.0, None)


def area_resize_depth(depth, size: tuple[int, int], *, min_valid: float = 0.5, name: str = "depth"):
    """Area resize of depth ``(..., H, W)`` to ``size = (h, w)`` over the valid pixels only;
    numpy in, numpy out; torch in, torch out.

    Each output pixel is the mean of the valid (> 0, finite) depths inside its area, so it
    stands for the ray through its own centre, as an area- or antialiased RGB resize does and
    as :func:`imac_data.core.cameras.rescale_intrinsics` assumes. (The nearest pixel of a 2x
    reduction lies a quarter output pixel off that ray.) It is 0 (unknown) where less than
    ``min_valid`` of the area is valid: an unknown pixel is never averaged in as a depth. Depths
    are averaged across an object's edge, as the RGB's colours are."""
    torch_in = is_torch(depth)
    depth, (h, w) = _resize_inputs(depth, size, name, torch_in)
    H, W = depth.shape[-2:]
    if (H, W) == (h, w):
        return depth
    wy, wx = _area_weights(h, H), _area_weights(w, W)
    if torch_in:
        torch = sys.modules["torch"]
        d = depth.to(torch.float64)
        wy, wx = (torch.as_tensor(a, dtype=torch.float64, device=d.device) for a in (wy, wx))
        valid = (torch.isfinite(d) & (d > 0)).to(torch.float64)
        d = torch.where(valid > 0, d, torch.zeros_like(d))
    else:
        d = np.asarray(depth, dtype=np.float64)
        valid = (np.isfinite(d) & (d > 0)).astype(np.float64)
        d = np.where(valid > 0, d, 0.0)
    total = wy @ (d * valid) @ wx.T
    covered = wy @ valid @ wx.T
    area = (H / h) * (W / w)
    keep = covered >= min_valid * area
    if torch_in:
        out = torch.where(keep, total / covered.clamp_min(1e-12), torch.zeros_like(total))
        return out.to(depth.dtype if depth.dtype.is_floating_point else torch.float32)
    out = np.where(keep, total / np.maximum(covered, 1e-12), 0.0)
    return out.astype(depth.dtype if depth.dtype.kind == "f" else np.float32)
