"""Contact images of many chunks at once: the accelerator's form of
:func:`~imac_data.core.contact.images.contact_chunk`, for training-time rollout, where every
step of a batch needs the contact images of a few hundred chunks whose reference frames the
model itself drew.

The same streams, settings and conventions as :func:`contact_chunk` (reference scene cloud with
the dilated robot mask removed and cropped to the workspace; r2s on future robot pixels, s2g on
scene pixels; percentile caps per chunk and stream; JET colours; s2g hole filling), on padded
``(B, ...)`` tensors. On a GPU the nearest-neighbour searches are blocked distance matrices (a few
thousand points a view at the world model's size), exact up to near-ties of the squared-distance
products (a matrix product on centred coordinates finds the winner, whose distance is then computed
exactly); on a CPU, where brute force is slow, one exact KD-tree per chunk. ``tests/test_contact.py``
checks both against ``contact_chunk`` with ``tolerance=None``.
Gripper points only (the rigs' :class:`~imac_data.core.contact.clouds.GripperSurface`); no
gripper masks."""

from __future__ import annotations

import contextlib

import torch

from imac_data.core.cameras import pixel_rays
from imac_data.core.contact.clouds import DEFAULT_DILATE_PX, dilate_mask
from imac_data.core.contact.images import (
    DEFAULT_FILL_PX,
    DEFAULT_PERCENTILE,
    EMPTY_CAP,
    MIN_CAP,
    ContactChunk,
    colorize,
    fill_sources,
    resolve_cap,
)
from imac_data.core.contact.nearest import NearestNeighbours
from imac_data.core.contact.workspace import as_workspace
from imac_data.errors import InputError

__all__ = ["contact_batch", "nearest_batch", "batch_caps"]

_PAD = 1.0e4  # metres: where an absent point sits; nothing real is this far from the robot
_FAR = 1.0e3  # a distance beyond this came from padding: nothing there (+inf)
# distance-matrix entries a block: on a GPU, few and large (1 GiB of float32), as a step's searches would otherwise
# be tens of thousands of small kernels
_BLOCK = {"cuda": 1 << 28, "cpu": 1 << 24}


def nearest_batch(query: torch.Tensor, points: torch.Tensor, *, method: str = "auto",
                  block: int | None = None) -> torch.Tensor:
    """Distance from each of ``query (B, N, 3)`` to the nearest of ``points (B, P, 3)`` (the same
    item), ``(B, N)``; +inf where an item has no points (``P = 0``, or every point padded away:
    coordinates of :data:`_PAD` and beyond count as absent). ``method``: ``"brute"`` (blocked
    distance matrices, what a GPU is fast at), ``"kdtree"`` (a KD-tree per item, exact, what a
    CPU is fast at), ``"auto"``: brute on CUDA, KD-trees elsewhere. ``block``: distance-matrix entries
    a brute-force block (default :data:`_BLOCK` of the device)."""
    if method not in ("auto", "brute", "kdtree"):
        raise InputError(f"nearest_batch: method must be 'auto', 'brute' or 'kdtree', got {method!r}")
    B, N = query.shape[:2]
    P = points.shape[1]
    out = torch.full((B, N), float("inf"), dtype=torch.float32, device=query.device)
    if N == 0 or P == 0:
        return out
    if method == "kdtree" or (method == "auto" and not query.is_cuda):
        for b in range(B):
            asked = query[b].abs().amax(dim=-1) < _PAD
            there = points[b][points[b].abs().amax(dim=-1) < _PAD]
            out[b, asked] = NearestNeighbours(there, method="kdtree", workers=1).distances(query[b][asked])
        return out
    # centred per item: the products' rounding then scales with the workspace, not with the world origin
    present = points.abs().amax(dim=-1) < _PAD
    count = present.sum(dim=1, keepdim=True).clamp(min=1)
    centre = (torch.where(present[..., None], points, 0.0).sum(dim=1, keepdim=True) / count[..., None])
    block = block or _BLOCK.get(query.device.type, _BLOCK["cpu"])
    with _full_precision(query.device.type):
        _nearest_blocks(query - centre, points - centre, out, block)
    return out.masked_fill_(out > _FAR, float("inf"))


@contextlib.contextmanager
def _full_precision(device_type: str):
    """float32 products whatever the trainer set (TF32 keeps 10 bits: centimetres on the argmin here)."""
    old = torch.get_float32_matmul_precision()
    torch.set_float32_matmul_precision("highest")
    try:
        with torch.autocast(device_type, enabled=False):
            yield
    finally:
        torch.set_float32_matmul_precision(old)


def _nearest_blocks(q: torch.Tensor, p: torch.Tensor, out: torch.Tensor, block: int) -> None:
    # the nearest point minimises |p|^2 - 2 q.p (|q|^2 is the row's constant): one batched product with its
    # bias, written once and read once by argmin, where cdist would also add |q|^2, clamp and take roots
    B, N = q.shape[:2]
    P = p.shape[1]
    p_squared = (p * p).sum(dim=-1)[:, None, :]
    items = max(1, block // max(1, N * P))
    rows = max(1, block // P) if items == 1 else N
    for b0 in range(0, B, items):
        b1 = min(B, b0 + items)
        for n0 in range(0, N, rows):
            n1 = min(N, n0 + rows)
            qb = q[b0:b1, n0:n1]
            nearest = torch.baddbmm(p_squared[b0:b1], qb, p[b0:b1].transpose(1, 2), alpha=-2.0).argmin(dim=-1)
            winner = torch.gather(p[b0:b1], 1, nearest[..., None].expand(-1, -1, 3))
            out[b0:b1, n0:n1] = (qb - winner).norm(dim=-1)


def _compact(points: torch.Tensor, keep: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``points (B, N, 3)`` with ``keep (B, N)`` -> the kept ones first, ``(B, K, 3)`` with K the
    largest count (the rest padded away), and their indexes ``(B, K)`` (``-1`` for padding)."""
    counts = keep.sum(dim=1)
    K = int(counts.max()) if keep.numel() else 0
    order = torch.sort(keep.to(torch.uint8), dim=1, descending=True, stable=True).indices[:, :K]
    taken = torch.arange(K, device=points.device)[None] < counts[:, None]
    gathered = torch.gather(points, 1, order[..., None].expand(-1, -1, 3))
    return torch.where(taken[..., None], gathered, _PAD), torch.where(taken, order, -1)


def _scatter(values: torch.Tensor, index: torch.Tensor, size: int) -> torch.Tensor:
    """``values (B, K)`` written at ``index (B, K)`` (``-1``: padding, dropped) of NaN rows ``(B, size)``."""
    out = torch.full((values.shape[0], size + 1), float("nan"), dtype=values.dtype, device=values.device)
    out.scatter_(1, torch.where(index >= 0, index, size), values)  # padding lands in the extra column
    return out[:, :size]


def _quantile(values: torch.Tensor, count: torch.Tensor, percentile: float) -> torch.Tensor:
    """numpy's linear-interpolation quantile of the first ``count`` entries of each row of
    ``values (B, N)`` sorted ascending (+inf counts as larger than everything), float64 ``(B,)``;
    NaN where ``count`` is 0, +inf where it lands on +inf (as ``images._quantile_with_inf``)."""
    pos = (percentile / 100.0) * (count.double() - 1).clamp(min=0)
    lo, hi = pos.floor().long(), pos.ceil().long()
    a = torch.gather(values, 1, lo[:, None].clamp(max=max(values.shape[1] - 1, 0)))[:, 0].double()
    b = torch.gather(values, 1, hi[:, None].clamp(max=max(values.shape[1] - 1, 0)))[:, 0].double()
    q = torch.where(hi == lo, a, a + (b - a) * (pos - lo))
    q = torch.where(torch.isinf(a) | torch.isinf(b), float("inf"), q)
    return torch.where(count > 0, q, float("nan"))


def batch_caps(values: torch.Tensor, present: torch.Tensor, percentile: float = DEFAULT_PERCENTILE) -> torch.Tensor:
    """Each row's percentile cap of ``values (B, N)`` where ``present`` (as ``images.chunk_caps``
    per stream: the percentile, +inf counted; the largest finite value if that is +inf; at least
    ``MIN_CAP``; ``EMPTY_CAP`` without a finite value), float32 ``(B,)``."""
    if values.shape[1] == 0:
        return torch.full((values.shape[0],), EMPTY_CAP, dtype=torch.float32, device=values.device)
    v = torch.where(present, values, float("inf"))  # absent values sort last, after the real +inf
    ordered = torch.sort(v, dim=1).values
    cap = _quantile(ordered, present.sum(dim=1), percentile)
    finite = present & torch.isfinite(values)
    largest = torch.where(finite, values, float("-inf")).amax(dim=1).double()
    cap = torch.where(torch.isinf(cap), largest, cap).clamp(min=MIN_CAP)
    return torch.where(finite.any(dim=1), cap, EMPTY_CAP).float()


def _world(depth: torch.Tensor, rays: torch.Tensor, T: torch.Tensor) -> torch.Tensor:
    """World points ``(..., V, HW, 3)`` of z-depth ``(..., V, HW)`` along ``rays (V, HW, 3)`` with
    camera-to-world poses ``T (..., V, 4, 4)``; NaN-free (invalid depth gives any finite point)."""
    d = torch.where(torch.isfinite(depth), depth, 0.0)
    p_cam = rays * d[..., None]
    return p_cam @ T[..., :3, :3].transpose(-1, -2) + T[..., None, :3, 3]


def contact_batch(ref_depth, K, ref_T_world_cam, ref_robot_mask, robot_depth, T_world_cam, gripper_points, *,
                  cap=None, percentile: float = DEFAULT_PERCENTILE, dilate_px: int = DEFAULT_DILATE_PX,
                  fill_px: int = DEFAULT_FILL_PX, workspace=None, method: str = "auto",
                  block: int | None = None) -> ContactChunk:
    """Both contact streams of B chunks, on the inputs' device, in full float32 whatever the caller set (a
    trainer's TF32 products would move the back-projected points by millimetres).

    ``ref_depth (B, V, H, W)`` metres (0 / non-finite = invalid), ``K (V, 3, 3)``,
    ``ref_T_world_cam (B, V, 4, 4)``, ``ref_robot_mask (B, V, H, W)``; future steps
    ``robot_depth (B, S, V, H, W)`` (0 = no robot), ``T_world_cam (B, S, V, 4, 4)``,
    ``gripper_points (B, S, M, 3)`` world. Options as :func:`contact_chunk`'s; ``method`` and
    ``block``: :func:`nearest_batch`. A chunk with an empty scene gets what ``allow_empty_scene`` gives there. Returns a
    :class:`ContactChunk` whose tensors have a leading B (``caps (B, 2)``)."""
    with _full_precision(torch.as_tensor(ref_depth).device.type):
        return _paint(ref_depth, K, ref_T_world_cam, ref_robot_mask, robot_depth, T_world_cam, gripper_points, cap,
                      percentile, dilate_px, fill_px, workspace, method, block)


def _paint(ref_depth, K, ref_T_world_cam, ref_robot_mask, robot_depth, T_world_cam, gripper_points, cap, percentile,
           dilate_px, fill_px, workspace, method, block) -> ContactChunk:
    depth = torch.as_tensor(ref_depth).float()
    if depth.ndim != 4:
        raise InputError(f"contact_batch: reference depth must be (B, V, H, W), got {tuple(depth.shape)}")
    B, V, H, W = depth.shape
    dev = depth.device
    K = torch.as_tensor(K, device=dev, dtype=torch.float32)
    T_ref = torch.as_tensor(ref_T_world_cam, device=dev, dtype=torch.float32)
    mask = torch.as_tensor(ref_robot_mask, device=dev).bool()
    rd = torch.as_tensor(robot_depth, device=dev).float()
    T = torch.as_tensor(T_world_cam, device=dev, dtype=torch.float32)
    grip = torch.as_tensor(gripper_points, device=dev, dtype=torch.float32)
    S = rd.shape[1] if rd.ndim == 5 else -1
    expected = {"K": (K, (V, 3, 3)), "reference poses": (T_ref, (B, V, 4, 4)), "reference robot mask": (mask, (B, V, H, W)),
                "future robot depth": (rd, (B, S, V, H, W)), "future camera poses": (T, (B, S, V, 4, 4))}
    for name, (x, shape) in expected.items():
        if tuple(x.shape) != shape:
            raise InputError(f"contact_batch: {name} must be {shape}, got {tuple(x.shape)}")
    if grip.ndim != 4 or tuple(grip.shape[:2]) != (B, S) or grip.shape[-1] != 3:
        raise InputError(f"contact_batch: gripper points must be (B, S, M, 3) = ({B}, {S}, M, 3), got {tuple(grip.shape)}")
    if not (torch.isfinite(K).all() and torch.isfinite(T_ref).all() and torch.isfinite(T).all()):
        raise InputError("contact_batch: K or camera poses contain NaN or inf")
    if not torch.isfinite(grip).all():
        raise InputError("contact_batch: gripper points contain NaN or inf")
    fixed = resolve_cap(cap)
    HW = H * W
    rays = pixel_rays(K, H, W)  # (V, HW, 3)

    # ---- the reference scene of every chunk (clouds.scene_cloud, batched)
    ws = as_workspace(workspace)
    removed = dilate_mask(mask, dilate_px)
    good = (torch.isfinite(depth) & (depth > 0)) if ws is None else ws.valid_depth(depth)
    valid = good & ~removed
    scene_points = _world(depth.reshape(B, V, HW), rays, T_ref)  # (B, V, HW, 3)
    region = ~removed
    if ws is not None:
        outside = valid & ~ws.contains(scene_points).reshape(B, V, H, W)
        valid, region = valid & ~outside, region & ~outside
    scene, scene_index = _compact(scene_points.reshape(B, V * HW, 3), valid.reshape(B, V * HW))

    # ---- r2s: every future robot pixel against its chunk's scene
    robot = (torch.isfinite(rd) & (rd > 0)).reshape(B, S * V * HW)
    robot_points = _world(rd.reshape(B, S, V, HW), rays, T).reshape(B, S * V * HW, 3)
    r_query, r_index = _compact(robot_points, robot)
    r_vals = nearest_batch(r_query, scene, method=method, block=block)
    r_present = r_index >= 0
    if fixed is not None:  # a fixed cap culls what lies beyond it, as contact_chunk's searches do
        r_vals = r_vals.masked_fill(r_vals > fixed[0], float("inf"))
    cap_r = (batch_caps(r_vals, r_present, percentile) if fixed is None else
             torch.full((B,), fixed[0], dtype=torch.float32, device=dev))
    r2s = _scatter(r_vals, r_index, S * V * HW)

    # ---- s2g: every chunk's scene against the gripper at each step
    P = scene.shape[1]
    s_vals = nearest_batch(scene[:, None].expand(B, S, P, 3).reshape(B * S, P, 3), grip.reshape(B * S, -1, 3),
                           method=method, block=block).reshape(B, S, P)
    s_present = (scene_index >= 0)[:, None].expand(B, S, P)
    if fixed is not None:
        s_vals = s_vals.masked_fill(s_vals > fixed[1], float("inf"))
    cap_s = (batch_caps(s_vals.reshape(B, S * P), s_present.reshape(B, S * P), percentile) if fixed is None else
             torch.full((B,), fixed[1], dtype=torch.float32, device=dev))
    s2g = _scatter(s_vals.reshape(B * S, P), scene_index.repeat_interleave(S, dim=0), V * HW).reshape(B, S, V * HW)

    r2s = r2s.reshape(B, S, V, H, W)
    s2g = s2g.reshape(B, S, V, H, W)
    r_rgb = colorize(r2s, cap_r.reshape(B, 1, 1, 1, 1))  # NaN (no robot) is black
    s_rgb = colorize(s2g, cap_s.reshape(B, 1, 1, 1, 1))
    if fill_px:
        # the hole filling of contact_chunk, one index map for every chunk and step
        dst, src = fill_sources(valid, region, int(fill_px))
        flat = s2g.transpose(0, 1).reshape(S, B * V * HW)
        flat.index_copy_(1, dst, flat.index_select(1, src))
        s2g = flat.reshape(S, B, V, H, W).transpose(0, 1)
        rgb = s_rgb.transpose(0, 1).reshape(S, B * V * HW, 3)
        rgb.index_copy_(1, dst, rgb.index_select(1, src))
        s_rgb = rgb.reshape(S, B, V, H, W, 3).transpose(0, 1)
    return ContactChunk(r2s=r2s, s2g=s2g.contiguous(), r2s_rgb=r_rgb, s2g_rgb=s_rgb.contiguous(),
                        caps=torch.stack([cap_r, cap_s], dim=1))
