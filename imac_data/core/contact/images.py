"""Contact images: the two robot-scene distance streams of iMaC (``docs/dataset-format.md``), as
torch functions used offline (the build) and online (the world model rebuilding them from its
own predicted depth).

Per chunk (reference frame t, steps k = 0..H): the reference scene cloud (every view's depth,
the dilated robot mask removed, cropped to the workspace); r2s paints each future robot pixel
with its distance to that cloud, s2g each reference scene pixel with its distance to the
gripper's surface samples at t+k; one cap per stream and chunk, colours JET of ``1 - d/cap``.
Distances are float32 metres within the certified tolerance of :mod:`~imac_data.core.contact.nearest`;
``+inf`` means nothing within reach."""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import torch

from imac_data.console import cpu_cores
from imac_data.core.contact.clouds import (  # re-exported: the contact streams' public API
    DEFAULT_DILATE_PX,
    GripperSurface,
    SceneCloud,
    camera_rays,
    dilate_mask,
    lift_pixels,
    scene_cloud,
)
from imac_data.core.contact.nearest import (
    DEFAULT_TOLERANCE,
    NearestNeighbours,
    TilePyramid,
    as_points,
    certified_distances,
    nearest_distances,
    resolve_tolerance,
)
from imac_data.core.contact.workspace import as_workspace
from imac_data.errors import InputError

__all__ = [
    "JET_LUT",
    "NearestNeighbours",
    "nearest_distances",
    "dilate_mask",
    "SceneCloud",
    "scene_cloud",
    "GripperSurface",
    "ContactChunk",
    "contact_chunk",
    "chunk_caps",
    "colorize",
    "chunk_plan",
    "EpisodeContact",
    "iter_episode_contact",
    "episode_contact",
    "DEFAULT_TOLERANCE",
]

DEFAULT_PERCENTILE = 99.0
DEFAULT_FILL_PX = 2
MIN_CAP = 1e-3  # metres; a percentile cap is never smaller (all-zero distances)
EMPTY_CAP = 1.0  # metres; the cap of a stream with no finite distance in the chunk
_R2S_STEPS = 2  # r2s steps per certified pass (tiles never cross steps, so the grouping is invisible)


# ----------------------------------------------------------------------------- colour map


def _jet_lut() -> np.ndarray:
    """matplotlib's ``jet`` (LinearSegmentedColormap, N=256) as a (256, 3) uint8 table,
    computed from its segment data so that matplotlib is not imported."""
    seg = {
        "red": ((0.0, 0.0), (0.35, 0.0), (0.66, 1.0), (0.89, 1.0), (1.0, 0.5)),
        "green": ((0.0, 0.0), (0.125, 0.0), (0.375, 1.0), (0.64, 1.0), (0.91, 0.0), (1.0, 0.0)),
        "blue": ((0.0, 0.5), (0.11, 1.0), (0.34, 1.0), (0.65, 0.0), (1.0, 0.0)),
    }
    x = np.linspace(0.0, 1.0, 256)
    channels = []
    for name in ("red", "green", "blue"):
        xs, ys = zip(*seg[name])
        channels.append(np.clip(np.interp(x, xs, ys), 0.0, 1.0))
    return (np.stack(channels, axis=1) * 255).astype(np.uint8)  # matplotlib's bytes=True rounding


JET_LUT = _jet_lut()
_LUT_CACHE: dict[str, torch.Tensor] = {}


def _lut(device: torch.device) -> torch.Tensor:
    lut = _LUT_CACHE.get(str(device))
    if lut is None:  # row 256 = no value (black)
        lut = _LUT_CACHE[str(device)] = torch.as_tensor(np.concatenate([JET_LUT, np.zeros((1, 3), np.uint8)]),
                                                        device=device)
    return lut


def colorize(distance: torch.Tensor, cap) -> torch.Tensor:
    """Distance map(s) ``(..., H, W)`` -> uint8 RGB ``(..., H, W, 3)``.

    ``level = floor(256 * (1 - clip(d / cap, 0, 1)))`` (clipped to 255) indexes
    matplotlib's ``jet`` (:data:`JET_LUT`): d = 0 -> dark red (127, 0, 0), d >= cap and
    +inf -> dark blue (0, 0, 127), NaN (no value) -> black. ``cap``: metres, a number
    or a tensor broadcastable to ``distance`` (e.g. ``(S, 1, 1, 1)``).
    """
    d = torch.as_tensor(distance)
    if not d.is_floating_point():
        raise InputError(f"colorize: distances must be floating point, got {d.dtype}")
    cap_t = torch.as_tensor(cap, dtype=d.dtype, device=d.device)
    if not (torch.isfinite(cap_t).all() and (cap_t > 0).all()):
        raise InputError(f"colorize: cap must be finite and > 0 metres, got {cap}")
    # level = floor(256 (1 - d / cap)) clipped to [0, 255]; +inf -> 0; NaN -> 256 (black)
    v = d * (-256.0 / cap_t) + 256.0
    level = v.clamp_(0, 255).to(torch.int64)
    level.masked_fill_(torch.isnan(d), 256)
    return _lut(d.device).index_select(0, level.reshape(-1)).reshape(*d.shape, 3)


# ----------------------------------------------------------------------------- chunks


@dataclass
class ContactChunk:
    """Contact images of the S steps of one chunk (all views of one rig, one resolution).

    ``r2s``, ``s2g``: ``(S, V, H, W)`` float32 metres (NaN = no value, +inf = nothing
    within reach); ``r2s_rgb``, ``s2g_rgb``: ``(S, V, H, W, 3)`` uint8 (:func:`colorize`
    with the chunk's caps); ``caps``: ``(2,)`` float32 metres, (r2s, s2g).
    """

    r2s: torch.Tensor
    s2g: torch.Tensor
    r2s_rgb: torch.Tensor
    s2g_rgb: torch.Tensor
    caps: torch.Tensor


def _quantile_with_inf(values: torch.Tensor, q: float) -> float:
    """numpy-style linear-interpolation quantile of a 1-D tensor that may hold +inf
    (NaN excluded). No size limit (unlike torch.quantile)."""
    n = values.numel()
    if n == 0:
        return math.nan
    pos = q / 100.0 * (n - 1)
    lo, hi = int(math.floor(pos)), int(math.ceil(pos))
    if values.device.type == "cpu":  # both order statistics in one partition: 2.4x faster than two kthvalue
        part = np.partition(values.detach().numpy(), [lo, hi])
        a, b = float(part[lo]), float(part[hi])
    else:
        a = float(values.kthvalue(lo + 1).values)
        b = float(values.kthvalue(hi + 1).values) if hi != lo else a
    if math.isinf(a) or math.isinf(b):
        return math.inf
    return a + (b - a) * (pos - lo)


def _stream_cap(values: torch.Tensor, percentile: float) -> float:
    """One stream's percentile cap (see :func:`chunk_caps`)."""
    v = values.reshape(-1)
    nan = torch.isnan(v)
    if bool(nan.any()):
        v = v[~nan]
    c = _quantile_with_inf(v, percentile)
    if math.isnan(c):
        return EMPTY_CAP
    if math.isinf(c):  # the finite values' largest, if there is one (a pass only in this case)
        finite = v[torch.isfinite(v)]
        if finite.numel() == 0:
            return EMPTY_CAP
        c = float(finite.max())
    return max(c, MIN_CAP)


def chunk_caps(r2s: torch.Tensor, s2g: torch.Tensor, percentile: float = DEFAULT_PERCENTILE) -> torch.Tensor:
    """The two percentile caps ``(2,)`` of a chunk's distances (NaN ignored).

    Per stream: the ``percentile`` of all its values (linear interpolation, +inf counts
    as larger than everything); if that lands on +inf, the largest finite value; never
    below :data:`MIN_CAP`; :data:`EMPTY_CAP` when the stream has no finite value.
    """
    return torch.tensor([_stream_cap(r2s, percentile), _stream_cap(s2g, percentile)], dtype=torch.float32)


def resolve_cap(cap) -> tuple[float, float] | None:
    """A ``cap`` argument checked: ``(r2s, s2g)`` metres, or None (each chunk's percentile)."""
    if cap is None:
        return None
    if isinstance(cap, (int, float, np.floating, np.integer)) and not isinstance(cap, bool):
        caps = (float(cap), float(cap))
    else:
        try:
            caps = tuple(float(c) for c in cap)
        except (TypeError, ValueError):
            raise InputError(f"cap must be None, metres, or (r2s, s2g) metres, got {cap!r}") from None
        if len(caps) != 2:
            raise InputError(f"cap must be None, metres, or (r2s, s2g) metres, got {cap!r}")
    if not all(math.isfinite(c) and c > 0 for c in caps):
        raise InputError(f"fixed contact caps must be finite and > 0 metres, got {cap!r}")
    return caps


_NEIGHBOURS = ((0, 1), (0, -1), (1, 0), (-1, 0), (1, 1), (1, -1), (-1, 1), (-1, -1))


def fill_sources(have: torch.Tensor, region: torch.Tensor, iterations: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Hole filling as an index map, for images ``(..., H, W)`` flattened: ``(dst, src)``
    such that ``values[dst] = values[src]`` densifies ``values`` inside ``region``.

    ``iterations`` times, every pixel of ``region`` without a value takes the value of
    its first neighbour (4-neighbours, then diagonals) that has one; ``src`` always
    points at an original pixel. Computed once per chunk (the scene pixels are the same
    for every step) and applied per step as one gather, so it copies values (no
    arithmetic: +inf stays +inf).
    """
    H, W = have.shape[-2:]
    source = torch.arange(have.numel(), device=have.device).reshape(have.shape)
    source = torch.where(have, source, torch.full_like(source, -1))
    have = have.clone()
    for _ in range(iterations):
        todo = region & ~have
        if not bool(todo.any()):
            break
        new_src, new_have = source.clone(), have.clone()
        for dy, dx in _NEIGHBOURS:  # 8 vectorised shifts, not a loop over pixels
            ys, yd = (slice(dy, H), slice(0, H - dy)) if dy >= 0 else (slice(0, H + dy), slice(-dy, H))
            xs, xd = (slice(dx, W), slice(0, W - dx)) if dx >= 0 else (slice(0, W + dx), slice(-dx, W))
            take = todo[..., yd, xd] & ~new_have[..., yd, xd] & have[..., ys, xs]
            new_src[..., yd, xd] = torch.where(take, source[..., ys, xs], new_src[..., yd, xd])
            new_have[..., yd, xd] |= take
        source, have = new_src, new_have
    filled = (source.reshape(-1) >= 0) & ~torch.arange(source.numel(), device=source.device).eq(source.reshape(-1))
    dst = torch.nonzero(filled)[:, 0]
    return dst, source.reshape(-1)[dst]


def _future_inputs(robot_depth, T_world_cam, gripper_points, gripper_mask, V, H, W, device):
    rd = torch.as_tensor(robot_depth, device=device)
    if rd.ndim != 4 or tuple(rd.shape[1:]) != (V, H, W):
        raise InputError(f"future robot depth must be (S, V, H, W) with (V, H, W) = {(V, H, W)} of the "
                         f"reference views, got {tuple(rd.shape)}")
    S = rd.shape[0]
    rd = rd.to(torch.float32)
    T = torch.as_tensor(T_world_cam, device=device, dtype=torch.float32)
    if T.shape != (S, V, 4, 4):
        raise InputError(f"future camera poses must be (S, V, 4, 4) = ({S}, {V}, 4, 4), got {tuple(T.shape)}")
    if not torch.isfinite(T).all():
        raise InputError("future camera poses contain NaN or inf")
    gm = None
    if gripper_mask is not None:
        gm = torch.as_tensor(gripper_mask, device=device).bool()
        if gm.shape != rd.shape:
            raise InputError(f"gripper mask must be (S, V, H, W) = {tuple(rd.shape)} like the future robot "
                             f"depth, got {tuple(gm.shape)}")
    if gripper_points is None:
        gp = [None] * S
    elif isinstance(gripper_points, torch.Tensor) or isinstance(gripper_points, np.ndarray):
        g = torch.as_tensor(gripper_points, device=device)
        if g.ndim != 3 or g.shape[0] != S or g.shape[-1] != 3:
            raise InputError(f"gripper points must be (S, M, 3) with S = {S} steps, got {tuple(g.shape)}")
        gp = [as_points(g[s], f"gripper points of step {s}") for s in range(S)]
    else:
        gp = list(gripper_points)
        if len(gp) != S:
            raise InputError(f"gripper points: {len(gp)} step(s) given for {S} future step(s)")
        gp = [as_points(g, f"gripper points of step {s}", device) for s, g in enumerate(gp)]
    if gm is None and gripper_points is None:
        raise InputError("no gripper: give gripper_points (e.g. GripperSurface samples) and/or gripper_mask")
    return rd, T, gp, gm


def contact_chunk(ref_depth, K, ref_T_world_cam, ref_robot_mask, robot_depth, T_world_cam,
                  gripper_points=None, *, gripper_mask=None, cap=None, percentile: float = DEFAULT_PERCENTILE,
                  dilate_px: int = DEFAULT_DILATE_PX, fill_px: int = DEFAULT_FILL_PX,
                  tolerance=DEFAULT_TOLERANCE, method: str = "auto", workers: int = -1,
                  allow_empty_scene: bool = False, device=None, cpu_threads: int | None = 1,
                  parallel: int | None = None, workspace=None) -> ContactChunk:
    """Both contact streams for the S steps of one chunk.

    Reference (frame t, all V views): ``ref_depth (V, H, W)`` metres, ``K (V, 3, 3)``,
    ``ref_T_world_cam (V, 4, 4)``, ``ref_robot_mask (V, H, W)`` (rendered at the state of
    t; dilated by ``dilate_px`` before removal). Future steps: ``robot_depth (S, V, H, W)``
    the rendered robot z-depth at each step's configuration (0 = no robot; its pixels are
    the robot mask and its back-projection the robot points), ``T_world_cam (S, V, 4, 4)``
    the camera poses at those steps (wrist cameras move), ``gripper_points`` ``(S, M, 3)``
    or a list of S ``(M_s, 3)`` world points (e.g. :meth:`GripperSurface.points`), and/or
    ``gripper_mask (S, V, H, W)`` marking gripper pixels of ``robot_depth`` whose points
    join the gripper cloud.

    ``cap``: None = per-stream ``percentile`` of this chunk's distances (:func:`chunk_caps`);
    a number or ``(r2s, s2g)`` = fixed caps in metres (distances beyond are culled to +inf).
    ``fill_px``: hole filling of s2g inside the scene mask (:func:`fill_sources`).
    ``workspace``: the crop of the reference scene (:func:`scene_cloud`; a
    :class:`~imac_data.core.contact.workspace.Workspace`, its dict form, or None = no crop): far
    background and saturated depth never enter the scene cloud or the caps.
    ``tolerance``: ``(metres, relative)``: every painted (not hole-filled) distance d'
    satisfies ``exact <= d' <= exact + max(metres, relative * exact)`` (certified pixel
    tiles, :func:`certified_distances`); ``None`` or 0 = exact per pixel (several times
    slower on the CPU).
    ``method``/``workers``: :class:`NearestNeighbours`. ``device``: where to compute
    (default: the device of ``ref_depth``). ``cpu_threads``: torch intra-op threads for
    the tensor work on the CPU during the call (restored afterwards; None = leave torch's
    setting). The default 1 is deliberate: that work is gathers and scatters on ~1e5-1e6
    elements, where torch's OpenMP pool gains little on an idle machine and, when the
    cores are shared (CI, data-loader workers), its spinning threads made a chunk 3-10x
    slower in our measurements. Instead, with ``cpu_threads`` set, the independent pieces
    (r2s; s2g of each step; each stream's cap and colours) run concurrently on up to
    ``parallel`` Python threads (default: one per available core); the KD-tree queries use
    ``workers`` threads. Neither changes the result.

    An empty scene cloud (all reference depth invalid or covered by the robot) raises
    :class:`InputError`, unless ``allow_empty_scene``: then r2s is +inf on every robot
    pixel (saturated colour) and s2g has no value (black). An empty gripper cloud at a
    step gives s2g = +inf there.
    """
    if device is None:
        device = torch.as_tensor(ref_depth).device
    device = torch.device(device)
    with _torch_threads(cpu_threads if device.type == "cpu" else None):
        return _contact_chunk(ref_depth, K, ref_T_world_cam, ref_robot_mask, robot_depth, T_world_cam,
                              gripper_points, gripper_mask, cap, percentile, dilate_px, fill_px, tolerance, method,
                              workers, allow_empty_scene, device, cpu_threads, parallel, workspace)


@contextlib.contextmanager
def _torch_threads(n: int | None):
    old = torch.get_num_threads()
    if n is None or int(n) == old:
        yield
        return
    torch.set_num_threads(int(n))
    try:
        yield
    finally:
        torch.set_num_threads(old)


def _contact_chunk(ref_depth, K, ref_T_world_cam, ref_robot_mask, robot_depth, T_world_cam, gripper_points,
                   gripper_mask, cap, percentile, dilate_px, fill_px, tolerance, method, workers, allow_empty_scene,
                   device, threads, parallel=None, workspace=None) -> ContactChunk:
    fixed = resolve_cap(cap)
    tol = resolve_tolerance(tolerance)
    if not (0.0 <= float(percentile) <= 100.0):
        raise InputError(f"cap percentile must be in [0, 100], got {percentile}")
    if int(fill_px) < 0:
        raise InputError(f"fill_px must be >= 0, got {fill_px}")
    scene = scene_cloud(ref_depth, K, ref_T_world_cam, ref_robot_mask, dilate_px=dilate_px, workspace=workspace,
                        device=device)
    V, H, W = scene.valid.shape
    HW = H * W
    Kt = torch.as_tensor(K, device=device, dtype=torch.float32)
    rd, T, gp, gm = _future_inputs(robot_depth, T_world_cam, gripper_points, gripper_mask, V, H, W, device)
    S = rd.shape[0]
    if len(scene.points) == 0 and not allow_empty_scene:
        d = torch.as_tensor(ref_depth, device=device)
        n_valid = int((torch.isfinite(d) & (d > 0)).sum())
        why = ("no reference pixel has valid depth (all 0 / non-finite)" if n_valid == 0 else
               f"all {n_valid} pixels with valid depth lie inside the (dilated by {dilate_px} px) robot mask"
               + ("" if scene.outside is None else
                  f", outside the workspace box or outside its depth range {list(as_workspace(workspace).depth_range)}"))
        raise InputError(f"reference scene is empty: {why}; check the depth units/validity, the robot "
                         "mask and the workspace, or pass allow_empty_scene=True")

    # ---- robot points of every step and view: back-projected robot depth
    rflat = torch.nonzero(rd.reshape(-1) > 0)[:, 0]  # index into (S, V, H, W); NaN is not > 0
    r_depth = rd.reshape(-1).index_select(0, rflat)
    finite = torch.isfinite(r_depth)  # +inf is no robot either (checked on the robot's pixels only)
    if not bool(finite.all()):
        rflat, r_depth = rflat[finite], r_depth[finite]
    image, pix = rflat // HW, rflat % HW  # image = step * V + view
    step = image // V
    rays = camera_rays(Kt, H, W)
    r_points = lift_pixels(r_depth, rays, T.reshape(S * V, 4, 4), image,
                           rflat - step * (V * HW))  # the ray: view * HW + pix

    r_cap, g_cap = fixed if fixed is not None else (None, None)
    g_flag = None if gm is None else gm.reshape(-1)[rflat]
    s_pyramid = None
    if tol is not None and len(scene.points):
        s_pyramid = TilePyramid(scene.points, scene.flat // HW, scene.flat % HW, V, H, W)
        s_pyramid.level(0, None)  # cached before the steps share it
    s_vals = torch.empty((S, len(scene.points)), dtype=torch.float32, device=device)

    r_vals = torch.empty(r_points.shape[0], dtype=torch.float32, device=device)
    first = torch.searchsorted(step, torch.arange(S + 1, device=device))  # steps are sorted
    scene_index: list = []

    def build_scene_index() -> None:
        # one scene index for the chunk, shared by every step's robot points
        scene_index.append(NearestNeighbours(scene.points, method=method, workers=workers))

    def robot_to_scene(s0: int, s1: int) -> None:
        # the robot points of steps s0..s1-1 (one contiguous block) against the scene
        a, b = int(first[s0]), int(first[s1])
        if a == b:
            return
        nn = scene_index[0]
        if tol is None:
            r_vals[a:b] = nn.distances(r_points[a:b], max_distance=r_cap).to(device)
        else:
            pyramid = TilePyramid(r_points[a:b], image[a:b] - s0 * V, pix[a:b], (s1 - s0) * V, H, W)
            r_vals[a:b] = certified_distances(pyramid, lambda p, bd: nn.query(p, max_distance=bd), tol, r_cap)

    def finish_r2s() -> tuple:
        cap_r = r_cap if r_cap is not None else _stream_cap(r_vals, percentile)
        maps = torch.full((S * V * HW,), math.nan, dtype=torch.float32, device=device)
        maps.index_copy_(0, rflat, r_vals)
        rgb = torch.zeros((S * V * HW, 3), dtype=torch.uint8, device=device)
        rgb.index_copy_(0, rflat, colorize(r_vals, cap_r))
        return maps.reshape(S, V, H, W), rgb.reshape(S, V, H, W, 3), cap_r

    def scene_to_gripper(s: int) -> None:
        # the (fixed) scene points against step s's gripper cloud
        parts = [] if gp[s] is None else [gp[s].to(device=device, dtype=torch.float32)]
        if g_flag is not None:
            parts.append(r_points[g_flag & (step == s)])
        g = torch.cat(parts) if parts else torch.zeros(0, 3, device=device)
        gnn = NearestNeighbours(g, method=method, workers=workers)
        if s_pyramid is None:
            s_vals[s] = gnn.distances(scene.points, max_distance=g_cap).to(device)
        else:
            s_vals[s] = certified_distances(s_pyramid, lambda p, b: gnn.query(p, max_distance=b), tol, g_cap)

    def finish_s2g() -> tuple:
        cap_s = g_cap if g_cap is not None else _stream_cap(s_vals, percentile)
        maps = torch.full((S, V * HW), math.nan, dtype=torch.float32, device=device)
        maps.index_copy_(1, scene.flat, s_vals)
        rgb = torch.zeros((S, V * HW, 3), dtype=torch.uint8, device=device)
        rgb.index_copy_(1, scene.flat, colorize(s_vals, cap_s))
        if fill_px and len(scene.points):
            dst, src = fill_sources(scene.valid, scene.mask, int(fill_px))
            maps.index_copy_(1, dst, maps.index_select(1, src))
            rgb.index_copy_(1, dst, rgb.index_select(1, src))
        return maps.reshape(S, V, H, W), rgb.reshape(S, V, H, W, 3), cap_s

    n_threads = (parallel or cpu_cores()) if device.type == "cpu" and threads is not None else 1
    if n_threads > 1:
        # On the CPU, the independent pieces (the scene index; r2s of groups of steps; s2g
        # of each step; then each stream's cap and colours) run on a few Python threads
        # (torch ops and KD-tree queries release the GIL) instead of torch's OpenMP pool.
        def task(fn, *args):
            torch.set_num_threads(threads)  # OpenMP thread counts are per thread
            return fn(*args)

        bounds = [*range(0, S, _R2S_STEPS), S]  # r2s a few steps per job, as on one thread
        parts = len(bounds) - 1
        with ThreadPoolExecutor(max_workers=min(n_threads, S + 1)) as pool:
            index_job = pool.submit(task, build_scene_index)
            jobs = [pool.submit(task, scene_to_gripper, 0)] if S else []
            index_job.result()  # the r2s jobs need it; s2g step 0 runs meanwhile
            jobs += [pool.submit(task, robot_to_scene, bounds[i], bounds[i + 1]) for i in range(parts)]
            jobs += [pool.submit(task, scene_to_gripper, s) for s in range(1, S)]
            for job in jobs:
                job.result()
            r_job, s_job = pool.submit(task, finish_r2s), pool.submit(task, finish_s2g)
            r2s, r_rgb, cap_r = r_job.result()
            s2g, s_rgb, cap_s = s_job.result()
    else:
        build_scene_index()
        for s0 in range(0, S, _R2S_STEPS):  # a few steps at a time: bounded temporaries, same tiles
            robot_to_scene(s0, min(s0 + _R2S_STEPS, S))
        for s in range(S):
            scene_to_gripper(s)
        r2s, r_rgb, cap_r = finish_r2s()
        s2g, s_rgb, cap_s = finish_s2g()
    caps = torch.tensor([cap_r, cap_s], dtype=torch.float32, device=device)
    return ContactChunk(r2s=r2s, s2g=s2g, r2s_rgb=r_rgb, s2g_rgb=s_rgb, caps=caps)


# ----------------------------------------------------------------------------- episodes


def chunk_plan(num_frames: int, chunk_size: int) -> list[tuple[int, list[int]]]:
    """``[(reference frame, [frames of the chunk])]`` for an episode of ``num_frames``.

    Chunk c: reference ``r = c * chunk_size``, frames ``r+1 .. r+chunk_size`` (clipped to
    the episode); chunk 0 also holds frame 0 itself (step k = 0). Every frame is in
    exactly one chunk, and its step is ``frame - reference``.
    """
    if int(num_frames) < 1:
        raise InputError(f"an episode needs at least one frame, got {num_frames}")
    if int(chunk_size) < 1:
        raise InputError(f"contact chunk size must be >= 1, got {chunk_size}")
    T, Hc = int(num_frames), int(chunk_size)
    plan = []
    for ref in range(0, max(T - 1, 1), Hc):
        frames = list(range(ref + 1, min(ref + Hc, T - 1) + 1))
        if ref == 0:
            frames = [0] + frames
        plan.append((ref, frames))
    return plan


@dataclass
class EpisodeContact:
    """Per-frame contact images of an episode (T frames): ``r2s``, ``s2g`` ``(T, V, H, W)``,
    ``r2s_rgb``, ``s2g_rgb`` ``(T, V, H, W, 3)``, ``caps (T, 2)`` (the caps of the frame's
    chunk), ``reference (T,)`` the frame each one's reference is, ``step (T,)`` = k."""

    r2s: torch.Tensor
    s2g: torch.Tensor
    r2s_rgb: torch.Tensor
    s2g_rgb: torch.Tensor
    caps: torch.Tensor
    reference: torch.Tensor
    step: torch.Tensor


def _frames(x, frames: list[int], name: str, T: int):
    if x is None:
        return None
    if isinstance(x, (torch.Tensor, np.ndarray)):
        if x.shape[0] != T:
            raise InputError(f"{name}: expected {T} frames in the first dimension, got {x.shape[0]}")
        return x[frames] if isinstance(x, torch.Tensor) else torch.as_tensor(x[frames])
    if len(x) != T:
        raise InputError(f"{name}: expected {T} frames, got {len(x)}")
    return [x[i] for i in frames]


def iter_episode_contact(depth, K, ref_T_world_cam, robot_mask, robot_depth, T_world_cam, gripper_points=None,
                         *, chunk_size: int, gripper_mask=None, **options
                         ) -> Iterator[tuple[int, list[int], ContactChunk]]:
    """Stream an episode chunk by chunk: yields ``(reference, frames, ContactChunk)``
    following :func:`chunk_plan` (frame 0 = step k = 0 of chunk 0).

    Per-frame inputs, first dimension T (tensors, arrays or sequences):

    * read at reference frames only: ``depth (T, V, H, W)`` (sensed or predicted),
      ``ref_T_world_cam (T, V, 4, 4)`` and ``robot_mask (T, V, H, W)`` (camera poses and
      robot render at the *observed* state);
    * read at every frame as a future step: ``robot_depth (T, V, H, W)`` and
      ``T_world_cam (T, V, 4, 4)`` (robot render and camera poses at the configuration to
      draw, e.g. the commanded one; for frame 0 this is step k = 0), ``gripper_points``
      ``(T, M, 3)`` or T ``(M_t, 3)``, optional ``gripper_mask (T, V, H, W)``.

    ``K (V, 3, 3)``; ``options``: :func:`contact_chunk`.
    """
    T = len(depth)
    for ref, frames in chunk_plan(T, chunk_size):
        chunk = contact_chunk(
            _frames(depth, [ref], "depth", T)[0], K, _frames(ref_T_world_cam, [ref], "reference poses", T)[0],
            _frames(robot_mask, [ref], "robot mask", T)[0],
            _frames(robot_depth, frames, "robot depth", T), _frames(T_world_cam, frames, "camera poses", T),
            _frames(gripper_points, frames, "gripper points", T),
            gripper_mask=_frames(gripper_mask, frames, "gripper mask", T), **options)
        yield ref, frames, chunk


def episode_contact(depth, K, ref_T_world_cam, robot_mask, robot_depth, T_world_cam, gripper_points=None, *,
                    chunk_size: int, gripper_mask=None, **options) -> EpisodeContact:
    """All frames of an episode at once, on the CPU (inputs: :func:`iter_episode_contact`;
    chunk rule: :func:`chunk_plan`). For long episodes stream with the iterator."""
    parts: dict[str, list] = {k: [] for k in ("r2s", "s2g", "r2s_rgb", "s2g_rgb", "caps", "reference", "step")}
    for ref, frames, c in iter_episode_contact(depth, K, ref_T_world_cam, robot_mask, robot_depth, T_world_cam,
                                               gripper_points, chunk_size=chunk_size, gripper_mask=gripper_mask,
                                               **options):
        n = len(frames)
        for k in ("r2s", "s2g", "r2s_rgb", "s2g_rgb"):
            parts[k].append(getattr(c, k).cpu())
        parts["caps"].append(c.caps.cpu()[None].expand(n, 2))
        parts["reference"].append(torch.full((n,), ref, dtype=torch.long))
        parts["step"].append(torch.tensor(frames, dtype=torch.long) - ref)
    return EpisodeContact(**{k: torch.cat(v) for k, v in parts.items()})
