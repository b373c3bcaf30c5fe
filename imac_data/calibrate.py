"""Calibration from the robot itself: refine camera poses by aligning the rendered robot
with the robot's pixels in the recorded frames.

Every recording already holds a calibration target: the robot, at joint angles we know.
Rendered (URDF + FK, :mod:`imac_data.render`) through a slightly wrong camera, its
silhouette misses the robot's pixels; this module moves the camera until they agree.
Functions here work on arrays and tensors; reading episodes, choosing the robot-pixel
source and writing files is :mod:`imac_data.refine`'s job.

What is refined
---------------
Per camera, one rigid 6-DoF pose: a fixed camera's ``T_world_cam`` or a mounted (wrist)
camera's ``T_link_cam``, optionally with its focal length (``fx`` and ``fy`` scaled
together, principal point kept). FK is known, so the cameras are independent problems.
The update is applied in the camera's own axes (OpenCV: x right, y down, z forward):
``T_world_cam(t) = T0_world_cam(t) @ exp(xi)``, which for a mounted camera is
``T_link_cam = T0_link_cam @ exp(xi)``. Pose changes and errors are reported in the same
axes (translation in mm, rotation vector in degrees), so "z" is always along the view.

Objective
---------
Over a set of frames (:func:`select_frames`: the robot covers much of the view, joint
configurations far apart), with ``G`` the robot pixels (a probability map in [0, 1]):

* **distance-field edge term**: at the rendered silhouette's boundary pixels, the distance
  field of ``G``'s silhouette (:func:`distance_field`) must equal the rendered silhouette's
  own field, i.e. boundary pixels land on boundary pixels. Comparing field with field (not
  with zero) keeps the optimum unbiased at the pixel level: the true pose scores exactly 0.
  Robust loss (``robust``, scale ``edge_scale_px``): Cauchy by default, so a rendered
  boundary far from any observed one (an occluded finger, a wrong mask) stops pulling;
* **silhouette IoU** between the rendered robot and ``G``, soft:
  ``sum(ab) / (sum(a^2) + sum(b^2) - sum(ab))`` of the blurred silhouettes, which is the IoU
  for binary ones and is maximal exactly when they agree.

``E = iou_weight * (1 - IoU) + edge_weight * mean loss(residual px)``. Measured
(``benchmarks/calibration_refine.py --ablation``): the IoU term only sees the robot where
the silhouettes already overlap or touch, so alone it stalls from a few centimetres off,
and added to the edge term it costs time without gaining accuracy; its default weight is
0. The edge term reaches everywhere the distance field does.

Coarse to fine: image scales ``levels`` (default 1/4, 1/2, 1; scales narrower than
``min_level_width`` px are skipped), each rendered with a margin around the image (``pad``)
so the robot just outside the view can move in. Both terms sample and splat with a
quadratic B-spline kernel (C1: no kinks at pixel centres, where every rendered pixel sits
at once when an iteration starts and where bilinear weights stall a line search).

Optimisers (``method``)
-----------------------
* ``"gradient"`` (default): torch autograd through a **soft silhouette**. Each iteration
  renders the robot exactly (ray casting) at the current pose, lifts the rendered pixels
  near the silhouette boundary to 3D (rendered z-depth) and moves them with the pose
  update ``xi``: the soft silhouette is their splat over the unchanged core of the render,
  the edge term samples the distance field at their projections. Both are differentiable
  in ``xi``; L-BFGS minimises them inside a trust region (``step_px``: image motion of the
  boundary, as a penalty), then the exact render decides whether the step is taken. At
  ``xi = 0`` the soft objective equals the exact one (tested).
* ``"nelder-mead"`` / ``"powell"``: derivative-free (scipy) on the exact objective, one
  exact render per evaluation (``10 * max_iterations`` per level).

The measured comparison that picked the default is printed by
``benchmarks/calibration_refine.py`` and summarised in the README ("Fixing a calibration").

Built-in robot cue
------------------
Without robot masks, :func:`image_edges` gives the image edges near the current overlay
(Canny, no learned model); ``refine_camera(..., edges=True)`` then pulls the rendered
outline onto the nearest edge (the edge term against the edges' distance transform; no
IoU). :mod:`imac_data.refine` repeats this with a shrinking search margin.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, fields

import cv2
import numpy as np
import torch

from imac_data.cameras import Camera
from imac_data.errors import InputError

__all__ = ["RefineConfig", "CameraFit", "METHODS", "se3_exp", "apply_update", "pose_change",
           "select_frames", "distance_field", "edge_distance", "silhouette_agreement", "refine_camera",
           "image_edges"]

METHODS = ("gradient", "nelder-mead", "powell")

# Optimisation units: translation in cm, rotation in degrees, focal in percent, so one
# unit moves the image by a comparable amount and the optimisers see a round problem.
_UNITS = np.array([0.01, 0.01, 0.01, math.radians(1.0), math.radians(1.0), math.radians(1.0), 0.01])
AXES = ("x_mm", "y_mm", "z_mm", "rx_deg", "ry_deg", "rz_deg")


@dataclass(frozen=True)
class RefineConfig:
    """How :func:`refine_camera` optimises (validated on construction; every field is a
    plain number, string or tuple, so ``RefineConfig(**saved)`` restores a saved one)."""

    method: str = "gradient"  # one of METHODS
    levels: tuple[float, ...] = (0.25, 0.5, 1.0)  # image scales, coarse to fine
    min_level_width: int = 48  # skip coarser levels than this (pixels)
    refine_focal: bool = False  # also scale fx, fy together
    iou_weight: float = 0.0  # measured: the IoU term slows convergence and costs time (benchmark --ablation)
    edge_weight: float = 0.1
    robust: str = "cauchy"  # edge loss: "cauchy" (log: far boundaries stop pulling) or "huber" (linear)
    edge_scale_px: float = 1.0  # the edge loss's scale (level px): residuals beyond it count less
    max_iterations: int = 12  # renders per level (gradient) / evaluations per level / 10 (derivative-free)
    step_px: float = 4.0  # trust region: the largest image motion of one gradient step (coarsest level px)
    fine_step_px: float = 2.0  # the same on the finer levels, which start close to their optimum
    tolerance_px: float = 0.02  # a level ends when a step moves the image less than this
    pad: float = 0.15  # rendered margin around the image, as a fraction of its larger side
    lbfgs_iterations: int = 6

    def __post_init__(self) -> None:
        def bad(name, why):
            raise InputError(f"RefineConfig.{name}: {why} (got {getattr(self, name)!r})")

        if self.method not in METHODS:
            bad("method", f"must be one of {METHODS}")
        if self.robust not in ("huber", "cauchy"):
            bad("robust", "must be 'huber' or 'cauchy'")
        levels = tuple(float(s) for s in self.levels) if isinstance(self.levels, (list, tuple)) else None
        if not levels or any(not (0 < s <= 1) for s in levels) or list(levels) != sorted(levels):
            bad("levels", "must be increasing image scales in (0, 1]")
        object.__setattr__(self, "levels", levels)
        for name in ("iou_weight", "edge_weight"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) >= 0):
                bad(name, "must be a finite number >= 0")
        if self.iou_weight == 0 and self.edge_weight == 0:
            bad("edge_weight", "iou_weight and edge_weight cannot both be 0")
        for name in ("edge_scale_px", "step_px", "fine_step_px", "tolerance_px"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) > 0):
                bad(name, "must be a finite number > 0")
        if not (0 <= self.pad <= 1):
            bad("pad", "must be in [0, 1]")
        for name in ("min_level_width", "max_iterations", "lbfgs_iterations"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                bad(name, "must be an integer >= 1")

    def to_dict(self) -> dict:
        return {f.name: (list(getattr(self, f.name)) if f.name == "levels" else getattr(self, f.name))
                for f in fields(self)}


@dataclass
class CameraFit:
    """The result of :func:`refine_camera` for one camera."""

    camera: Camera  # refined
    initial: Camera
    update: np.ndarray  # (7,) total update in optimisation units (cm, deg, focal %)
    history: list[dict] = field(default_factory=list)  # one entry per accepted step / level
    renders: int = 0  # exact renders of the frame set
    wall_s: float = 0.0
    cpu_s: float = 0.0


# ----------------------------------------------------------------------------- SE(3)


def se3_exp(xi: torch.Tensor) -> torch.Tensor:
    """``(..., 6)`` twists ``(v, omega)`` (metres, radians) -> ``(..., 4, 4)`` rigid transforms
    (differentiable)."""
    v, w = xi[..., :3], xi[..., 3:6]
    A = torch.zeros(*xi.shape[:-1], 4, 4, dtype=xi.dtype, device=xi.device)
    A[..., 0, 1], A[..., 0, 2], A[..., 1, 2] = -w[..., 2], w[..., 1], -w[..., 0]
    A[..., 1, 0], A[..., 2, 0], A[..., 2, 1] = w[..., 2], -w[..., 1], w[..., 0]
    A[..., :3, 3] = v
    return torch.linalg.matrix_exp(A)


def _update_matrix(p: np.ndarray) -> np.ndarray:
    xi = torch.as_tensor(np.asarray(p[:6], dtype=np.float64) * _UNITS[:6])
    return se3_exp(xi).numpy()


def apply_update(camera: Camera, p: Sequence[float]) -> Camera:
    """``camera`` moved by the update ``p`` (optimisation units: ``(x, y, z)`` cm, ``(rx, ry, rz)``
    degrees in the camera's axes, then optionally the focal change in percent)."""
    p = np.zeros(7) + np.pad(np.asarray(p, dtype=np.float64), (0, 7 - len(p)))
    M = _update_matrix(p)
    K = camera.K.copy()
    s = math.exp(p[6] * _UNITS[6])
    K[0, :2] *= s
    K[1, 1] *= s
    if camera.is_mounted:
        return Camera(camera.name, K, camera.width, camera.height, link=camera.link, T_link_cam=camera.T_link_cam @ M)
    return Camera(camera.name, K, camera.width, camera.height, T_world_cam=camera.T_world_cam @ M)


def _parent_pose(camera: Camera) -> np.ndarray:
    return camera.T_link_cam if camera.is_mounted else camera.T_world_cam


def pose_change(before: Camera | np.ndarray, after: Camera | np.ndarray) -> dict[str, float]:
    """Per-axis change from ``before`` to ``after`` in ``before``'s camera axes (OpenCV: x right,
    y down, z forward): translation of the camera centre in mm, rotation vector in degrees,
    plus the norms (``t_mm``, ``r_deg``). Takes two cameras (their ``T_world_cam`` or
    ``T_link_cam``) or two 4x4 camera-to-parent matrices."""
    from scipy.spatial.transform import Rotation

    A = _parent_pose(before) if isinstance(before, Camera) else np.asarray(before, dtype=np.float64)
    B = _parent_pose(after) if isinstance(after, Camera) else np.asarray(after, dtype=np.float64)
    D = np.linalg.inv(A) @ B
    t = D[:3, 3] * 1000.0
    r = np.degrees(Rotation.from_matrix(D[:3, :3]).as_rotvec())
    out = {k: float(v) for k, v in zip(AXES, (*t, *r))}
    out["t_mm"] = float(np.linalg.norm(t))
    out["r_deg"] = float(np.linalg.norm(r))
    return out


# ----------------------------------------------------------------------------- frames


def select_frames(q: np.ndarray, coverage: np.ndarray, count: int = 8, *, min_coverage: float = 0.01,
                  min_separation: float = 0.1, camera: str = "") -> np.ndarray:
    """Pick ``count`` frames for calibration: the robot covers much of the view and the joint
    configurations are far apart (different depths and directions constrain every axis).

    ``q`` ``(M, D)`` joint vectors of the candidate frames, ``coverage`` ``(M,)`` the fraction
    of each view the robot covers. Frames with coverage below ``min_coverage`` do not
    count; of the rest, the better-covered three quarters are candidates. Greedy
    farthest-point sampling in joint space, starting at the best-covered frame; a frame
    closer than ``min_separation`` (joint-vector units, radians for revolute joints) to a
    chosen one is not a distinct pose. Returns candidate indices (sorted) or raises
    :class:`InputError` when the robot is not visible or too few distinct poses exist.
    """
    q = np.asarray(q, dtype=np.float64)
    coverage = np.asarray(coverage, dtype=np.float64)
    where = f" in camera {camera!r}" if camera else ""
    if q.ndim != 2 or coverage.shape != (len(q),):
        raise InputError(f"select_frames: q must be (M, D) and coverage (M,), got {q.shape} and {coverage.shape}")
    if count < 1:
        raise InputError(f"select_frames: count must be >= 1, got {count}")
    visible = np.flatnonzero(coverage >= min_coverage)
    if len(visible) == 0:
        best = float(coverage.max()) if len(coverage) else 0.0
        raise InputError(
            f"no robot visible{where}: in none of the {len(coverage)} candidate frames does the robot cover "
            f"{100 * min_coverage:.1f}% of the view (at most {100 * best:.2f}%). Refinement aligns the robot's "
            "silhouette, so it needs frames that show the robot (check the camera name and the robot-pixel source)")

    def greedy(pool: np.ndarray) -> list[int]:
        chosen = [int(pool[np.argmax(coverage[pool])])]
        dist = np.linalg.norm(q[pool] - q[chosen[0]], axis=1)
        while len(chosen) < count:
            k = int(np.argmax(dist))
            if dist[k] < min_separation:
                break
            chosen.append(int(pool[k]))
            dist = np.minimum(dist, np.linalg.norm(q[pool] - q[pool[k]], axis=1))
        return chosen

    good = visible[coverage[visible] >= np.quantile(coverage[visible], 0.25)]
    chosen = greedy(good)
    if len(chosen) < count:
        chosen = greedy(visible)
    if len(chosen) < count:
        raise InputError(
            f"too few distinct poses{where}: the frames that show the robot hold only {len(chosen)} joint "
            f"configuration(s) at least {min_separation} apart, and refinement needs {count}. A camera pose is "
            "only pinned down by views of the robot in different configurations: use episodes where the arms "
            "move, more episodes, or ask for fewer frames (fewer constrain the pose less)")
    return np.sort(np.array(chosen, dtype=np.int64))


# ----------------------------------------------------------------------------- fields


def distance_field(mask: np.ndarray) -> np.ndarray:
    """Pixel-centre distance field of a silhouette ``(..., H, W)`` (bool): for pixels outside,
    the distance to the nearest silhouette pixel (>= 1); inside, 1 minus the distance to the
    nearest outside pixel (<= 0). Inner boundary pixels are 0 (diagonal-only ones 1 - sqrt 2),
    the outer boundary 1; bilinear interpolation crosses 1/2 on the silhouette's edge. A view
    without any silhouette pixel gets a large constant."""
    mask = np.asarray(mask, dtype=bool)
    out = np.empty(mask.shape, dtype=np.float32)
    flat_m, flat_o = mask.reshape(-1, *mask.shape[-2:]), out.reshape(-1, *mask.shape[-2:])
    big = float(sum(mask.shape[-2:]))
    for m, o in zip(flat_m, flat_o):
        if not m.any():
            o[:] = big
            continue
        if m.all():
            o[:] = -big
            continue
        u8 = m.astype(np.uint8)
        inside = cv2.distanceTransform(u8, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
        outside = cv2.distanceTransform(1 - u8, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
        np.copyto(o, np.where(m, 1.0 - inside, outside))
    return out


def edge_distance(edges: np.ndarray) -> np.ndarray:
    """Distance (px) of every pixel to the nearest edge pixel of ``(N, H, W)`` edge maps (0 on an
    edge; a view without edges gets a large constant)."""
    out = np.empty(edges.shape, dtype=np.float32)
    for e, o in zip(edges, out):
        if e.any():
            np.copyto(o, cv2.distanceTransform((~e).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE))
        else:
            o[:] = float(sum(e.shape))
    return out


def _boundary(mask: np.ndarray) -> np.ndarray:
    """Inner boundary pixels (8-neighbourhood) of masks ``(N, H, W)``; the image border is
    not a boundary (the silhouette goes on outside the view)."""
    out = np.empty_like(mask)
    k = np.ones((3, 3), np.uint8)
    for m, o in zip(mask, out):
        er = cv2.erode(m.astype(np.uint8), k, borderType=cv2.BORDER_REPLICATE)
        np.logical_and(m, er == 0, out=o)
    return out


def silhouette_agreement(rendered: np.ndarray, target: np.ndarray, *, edges: bool = False) -> dict[str, float]:
    """How well rendered robot masks ``(N, H, W)`` match the robot pixels ``target`` (probability,
    thresholded at 1/2): mean IoU over frames, and the boundary residual in pixels (mean over
    both silhouettes' boundary pixels of the distance to the other silhouette's boundary, the
    symmetric chamfer distance). With ``edges=True`` ``target`` is an edge map: no IoU, and the
    residual is the rendered outline's mean distance to the nearest edge."""
    r = np.asarray(rendered, dtype=bool)
    if edges:
        b = _boundary(r)
        d = edge_distance(np.asarray(target, dtype=bool))[b]
        d = d if len(d) else np.array([np.nan])
        return {"iou": None, "iou_per_frame": None, "boundary_px": float(d.mean()),
                "boundary_px_p90": float(np.quantile(d, 0.9))}
    g = np.asarray(target) >= 0.5
    inter = np.logical_and(r, g).sum(axis=(-1, -2))
    union = np.logical_or(r, g).sum(axis=(-1, -2))
    ious = np.where(union > 0, inter / np.maximum(union, 1), np.nan)
    dists = []
    for a, b in ((_boundary(r), _boundary(g)), (_boundary(g), _boundary(r))):
        for ea, eb in zip(a, b):
            if ea.any() and eb.any():
                dt = cv2.distanceTransform((~eb).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
                dists.append(dt[ea])
    d = np.concatenate(dists) if dists else np.array([np.nan])
    return {"iou": float(np.nanmean(ious)) if np.isfinite(ious).any() else float("nan"),
            "iou_per_frame": [float(x) for x in ious],
            "boundary_px": float(d.mean()), "boundary_px_p90": float(np.quantile(d, 0.9))}


# ----------------------------------------------------------------------------- levels

# The smoothing kernel of both objective terms: the quadratic B-spline, whose weights for a
# point at fractional offset f in [-1/2, 1/2) from its nearest pixel centre are
# (1/2 (1/2 - f)^2, 3/4 - f^2, 1/2 (1/2 + f)^2) on the pixels at -1, 0, +1. They sum to 1 and
# are C1 in f, so splatting and sampling with them has no kinks at pixel centres (bilinear
# weights have one there, for every rendered pixel at once, which stalls a line search).
# At integer positions it is the blur (1/8, 3/4, 1/8) applied to both sides alike.
_BLUR = np.array([0.125, 0.75, 0.125], dtype=np.float32)


def _blur(a: np.ndarray) -> np.ndarray:
    """The kernel at integer positions, per frame of ``(N, H, W)``; outside the image counts as 0."""
    out = np.empty(a.shape, dtype=np.float32)
    for x, o in zip(a, out):
        cv2.sepFilter2D(x.astype(np.float32), cv2.CV_32F, _BLUR, _BLUR, dst=o, borderType=cv2.BORDER_CONSTANT)
    return out


def _bspline(uv: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, list[tuple[int, torch.Tensor]], list]:
    c = torch.floor(uv + 0.5)
    f = uv - c
    w = [0.5 * (0.5 - f) ** 2, 0.75 - f * f, 0.5 * (0.5 + f) ** 2]
    c = c.long()
    return c[:, 0], c[:, 1], [(d - 1, w[d][:, 0]) for d in range(3)], [(d - 1, w[d][:, 1]) for d in range(3)]


def _sample(values: torch.Tensor, n: torch.Tensor, uv: torch.Tensor, h: int, w: int
            ) -> tuple[torch.Tensor, torch.Tensor]:
    """B-spline-weighted sample of flattened ``(N*h*w,)`` images at frame ``n``, pixel ``uv``
    (differentiable in uv). Returns the values and which samples lie inside the image."""
    cx, cy, wx, wy = _bspline(uv)
    ok = (cx >= 1) & (cy >= 1) & (cx < w - 1) & (cy < h - 1)
    cx, cy = cx.clamp(1, w - 2), cy.clamp(1, h - 2)
    out = torch.zeros(len(uv), dtype=uv.dtype)
    for dy, ay in wy:
        row = (n * h + cy + dy) * w + cx
        for dx, ax in wx:
            out = out + values[row + dx] * (ax * ay)
    return out, ok


def _splat(lut: torch.Tensor, n: torch.Tensor, uv: torch.Tensor, h: int, w: int, size: int) -> torch.Tensor:
    """B-spline splat of unit weights at ``uv`` (frame ``n``) into the ``size`` pixels that ``lut``
    (flattened ``(N*h*w,)`` image -> slot, -1 = not tracked) tracks: the adjoint of :func:`_sample`."""
    cx, cy, wx, wy = _bspline(uv)
    dens = torch.zeros(size + 1, dtype=uv.dtype)  # the last slot collects everything untracked
    for dy, ay in wy:
        y = cy + dy
        oky = (y >= 0) & (y < h)
        row = (n * h + y.clamp(0, h - 1)) * w
        for dx, ax in wx:
            x = cx + dx
            ok = oky & (x >= 0) & (x < w)
            slot = lut[row + x.clamp(0, w - 1)]
            slot = torch.where(ok & (slot >= 0), slot, size)
            dens = dens.index_add(0, slot, ax * ay)
    return dens[:size]


@dataclass
class _Level:
    """One resolution of the problem: the padded camera to render, the observed robot pixels."""

    scale: float
    h: int
    w: int
    m: int  # margin (px) on each side of the rendered image
    target: np.ndarray  # (N, h, w) float32 robot probability
    field: torch.Tensor  # (N*h*w,) distance field of target >= 1/2, flattened (sampled with the kernel)
    field_blurred: np.ndarray  # (N*h*w,) the same, blurred (its samples at pixel centres)
    soft: np.ndarray  # (N*h*w,) blurred target
    soft_sq: float  # sum of its squares
    edges: bool  # target is an edge map: field = distance to the nearest edge, no IoU term


def _make_level(camera: Camera, target: np.ndarray, scale: float, pad: float, edges: bool) -> _Level:
    H, W = target.shape[1:]
    h, w = max(1, round(H * scale)), max(1, round(W * scale))
    if (h, w) == (H, W):
        t = target.astype(np.float32)
    else:
        t = np.stack([cv2.resize(x.astype(np.float32), (w, h), interpolation=cv2.INTER_AREA) for x in target])
    m = int(math.ceil(pad * max(h, w)))
    if edges:  # an edge pixel anywhere in a coarse pixel makes it an edge pixel
        field = edge_distance(t > 0)
        soft = np.zeros(t.size, np.float32)
    else:
        field = distance_field(t >= 0.5)
        soft = _blur(t).reshape(-1)
    return _Level(scale, h, w, m, t, torch.from_numpy(field.reshape(-1)), _blur(field).reshape(-1),
                  soft, float(np.dot(soft, soft)), edges)


def _level_camera(camera: Camera, lv: _Level) -> Camera:
    c = camera if (camera.height, camera.width) == (lv.h, lv.w) else camera.rescaled(lv.w, lv.h)
    K = c.K.copy()
    K[0, 2] += lv.m
    K[1, 2] += lv.m
    return Camera(c.name, K, lv.w + 2 * lv.m, lv.h + 2 * lv.m, c.T_world_cam, c.link, c.T_link_cam)


@dataclass
class _View:
    """The exact render at one pose (padded) and its objective."""

    mask: np.ndarray  # (N, h + 2m, w + 2m) bool
    depth: np.ndarray
    inside: np.ndarray  # distance of silhouette pixels to the nearest outside pixel
    field: np.ndarray  # blurred distance field of the render
    energy: float = 0.0
    iou: float = 0.0  # soft IoU (binary IoU of the blurred silhouettes' supports is not it)
    edge: float = 0.0  # mean Huber edge residual, px


def _render(renderer, camera: Camera, q: torch.Tensor, lv: _Level, cfg: RefineConfig) -> _View:
    out = renderer.render(q, {camera.name: _level_camera(camera, lv)})[camera.name]
    mask = out.mask.cpu().numpy()
    inside = np.empty(mask.shape, np.float32)
    for m, o in zip(mask, inside):
        np.copyto(o, cv2.distanceTransform(m.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE))
    v = _View(mask, out.depth.cpu().numpy(), inside, _blur(distance_field(mask)))
    v.energy, v.iou, v.edge = _exact_energy(v, lv, cfg)
    return v


def _crop(a: np.ndarray, lv: _Level) -> np.ndarray:
    return a[:, lv.m:lv.m + lv.h, lv.m:lv.m + lv.w]


def _robust(r: torch.Tensor, cfg: RefineConfig) -> torch.Tensor:
    """The edge loss of residuals ``r`` (px): quadratic near 0 (r^2 / 2), then Huber (linear) or
    Cauchy (logarithmic: a boundary far from any observed one stops pulling, which is what
    occlusions and wrong masks need)."""
    c = cfg.edge_scale_px
    if cfg.robust == "cauchy":
        return 0.5 * c * c * torch.log1p((r / c) ** 2)
    a = r.abs()
    return torch.where(a <= c, 0.5 * r * r, c * (a - 0.5 * c))


def _contour(v: _View, lv: _Level) -> np.ndarray:
    """Boundary pixels of the render whose 3x3 neighbourhood lies inside the image."""
    c = v.mask & (v.inside < 1.5)
    keep = np.zeros(c.shape[1:], dtype=bool)
    keep[lv.m + 1:lv.m + lv.h - 1, lv.m + 1:lv.m + lv.w - 1] = True
    return c & keep


def _soft_iou(ab: float, aa: float, bb: float) -> float:
    """sum(ab) / (sum(a^2) + sum(b^2) - sum(ab)): the IoU for binary a, b; for soft ones it is
    maximal (1) exactly when a = b, and smooth."""
    den = aa + bb - ab
    return ab / den if den > 0 else 0.0


def _exact_energy(v: _View, lv: _Level, cfg: RefineConfig) -> tuple[float, float, float]:
    """The objective at a rendered pose (what the soft objective equals at ``xi = 0``)."""
    a = _crop(_blur(v.mask), lv).reshape(-1)  # the silhouette just outside the image blurs in
    iou = _soft_iou(float(np.dot(a, lv.soft)), float(np.dot(a, a)), lv.soft_sq)
    n, yy, xx = np.nonzero(_contour(v, lv))
    if len(n):
        own = np.zeros(len(n), np.float32) if lv.edges else v.field[n, yy, xx]
        f = lv.field_blurred[(n * lv.h + yy - lv.m) * lv.w + xx - lv.m]
        edge = float(_robust(torch.from_numpy(f - own), cfg).mean())
    else:
        edge = float(cfg.edge_scale_px * lv.w)  # nothing rendered in the view: as bad as it gets
    return cfg.iou_weight * (1.0 - iou) + cfg.edge_weight * edge, iou, edge


# ----------------------------------------------------------------------------- gradient step


class _SoftSilhouette:
    """The differentiable objective around one exact render: rendered pixels near the silhouette
    boundary lifted to 3D (rendered z-depth) and moved by the update, splatted over the
    unchanged core of the render; edge pixels sample the target's distance field.

    Only pixels the update can change are tracked (within the trust region's reach of the
    boundary); the rest of the sums are constants, so one evaluation costs O(boundary).
    Heavy arrays are float32 (pixel coordinates to 1e-4 px); the update itself is float64.
    """

    def __init__(self, v: _View, camera: Camera, lv: _Level, cfg: RefineConfig, step_px: float):
        self.cfg, self.lv, self.refine_focal = cfg, lv, cfg.refine_focal
        reach = step_px + 1.5  # a pixel this deep stays inside after a step (trust region)
        core = v.mask & (v.inside > reach)
        band = v.mask & ~core
        grow = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * int(reach + 2) + 1,) * 2)
        active = _crop(np.stack([cv2.dilate(b.astype(np.uint8), grow) for b in band]) > 0, lv).reshape(-1)
        core_soft = _crop(_blur(core), lv).reshape(-1)
        cam = _level_camera(camera, lv)
        self.K = torch.as_tensor(cam.K, dtype=torch.float64)
        Kinv = np.linalg.inv(cam.K)

        def lift(sel):
            n, y, x = np.nonzero(sel)
            z = v.depth[n, y, x].astype(np.float64)
            rays = np.stack([x, y, np.ones_like(x)], 1).astype(np.float64) @ Kinv.T
            return torch.from_numpy(n), torch.from_numpy((rays * z[:, None]).astype(np.float32))

        self.n_band, self.X_band = lift(band)
        contour = _contour(v, lv)
        self.n_edge, self.X_edge = lift(contour)
        n, y, x = np.nonzero(contour)
        self.uv_edge = torch.from_numpy(np.stack([x - lv.m, y - lv.m], 1).astype(np.float32))
        self.own_field = torch.zeros(len(n)) if lv.edges else torch.from_numpy(v.field[n, y, x])
        g = lv.soft
        slots = np.flatnonzero(active)
        lut = np.full(g.shape, -1, dtype=np.int64)
        lut[slots] = np.arange(len(slots))
        self.lut, self.size = torch.from_numpy(lut), len(slots)
        self.g_active = torch.from_numpy(g[slots])
        self.core_active = torch.from_numpy(core_soft[slots])
        rest = ~active
        self.ab_rest = float(np.dot(core_soft[rest], g[rest]))
        self.aa_rest = float(np.dot(core_soft[rest], core_soft[rest]))
        self.m = lv.m

    def project(self, X: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
        """Image pixel coordinates (unpadded level image) of camera-frame points after update ``p``."""
        M = se3_exp(p[:6] * torch.as_tensor(_UNITS[:6])).to(X.dtype)
        Xn = (X - M[:3, 3]) @ M[:3, :3]  # M^-1 X, with X as rows
        K = self.K
        s = torch.exp(p[6] * _UNITS[6]) if self.refine_focal else torch.ones((), dtype=torch.float64)
        fx, skew, fy = (s * K[0, 0]).to(X.dtype), (s * K[0, 1]).to(X.dtype), (s * K[1, 1]).to(X.dtype)
        z = Xn[:, 2].clamp_min(1e-6)
        u = (fx * Xn[:, 0] + skew * Xn[:, 1]) / z + float(K[0, 2] - self.m)
        vv = fy * Xn[:, 1] / z + float(K[1, 2] - self.m)
        return torch.stack([u, vv], 1)

    def energy(self, p: torch.Tensor) -> torch.Tensor:
        cfg, lv = self.cfg, self.lv
        e = torch.zeros((), dtype=torch.float64)
        if cfg.iou_weight > 0:
            uv = self.project(self.X_band, p)
            a = self.core_active + _splat(self.lut, self.n_band, uv, lv.h, lv.w, self.size)
            ab = self.ab_rest + (a * self.g_active).sum(dtype=torch.float64)
            aa = self.aa_rest + (a * a).sum(dtype=torch.float64)
            e = e + cfg.iou_weight * (1.0 - ab / (aa + lv.soft_sq - ab).clamp_min(1e-9))
        if cfg.edge_weight > 0 and len(self.X_edge):
            uv = self.project(self.X_edge, p)
            f, ok = _sample(lv.field, self.n_edge, uv, lv.h, lv.w)
            r = (f - self.own_field)[ok]
            if len(r):
                e = e + cfg.edge_weight * _robust(r, cfg).mean(dtype=torch.float64)
        return e

    def rms_motion(self, p: torch.Tensor) -> torch.Tensor:
        """Root-mean-square image motion (level px) of the boundary pixels under update ``p``."""
        if not len(self.X_edge):
            return torch.zeros((), dtype=torch.float64)
        d = self.project(self.X_edge, p) - self.uv_edge
        return ((d * d).sum(dim=1).mean(dtype=torch.float64) + 1e-12).sqrt()

    def max_motion(self, p: torch.Tensor) -> float:
        """The largest image motion (level px) the update causes on the boundary pixels."""
        if not len(self.X_edge):
            return 0.0
        with torch.no_grad():
            zero = torch.zeros_like(p)
            return float((self.project(self.X_edge, p) - self.project(self.X_edge, zero)).norm(dim=1).max())


def _gradient_level(renderer, camera: Camera, q: torch.Tensor, lv: _Level, cfg: RefineConfig, step_px: float,
                    fit: CameraFit, log: Callable[[str], None] | None) -> Camera:
    """Iterate: exact render -> soft objective around it -> L-BFGS inside the trust region ->
    the exact render judges the step (halved until it helps; the plain gradient direction as a
    last resort, since far along an L-BFGS direction the landscape can hide a bump)."""
    n_par = 7 if cfg.refine_focal else 6
    v = _render(renderer, camera, q, lv, cfg)
    fit.renders += 1
    mask = torch.zeros(7, dtype=torch.float64)
    mask[:n_par] = 1.0
    for it in range(cfg.max_iterations):
        soft = _SoftSilhouette(v, camera, lv, cfg, step_px)
        p = torch.zeros(7, dtype=torch.float64, requires_grad=True)
        opt = torch.optim.LBFGS([p], lr=1.0, max_iter=cfg.lbfgs_iterations, line_search_fn="strong_wolfe",
                                tolerance_grad=1e-10, tolerance_change=1e-12)

        def closure():
            opt.zero_grad()
            x = p * mask
            # the trust region as a penalty, so L-BFGS searches where the soft model holds
            e = soft.energy(x) + 10.0 * torch.relu(soft.rms_motion(x) - step_px) ** 2
            e.backward()
            return e

        opt.step(closure)
        step = (p.detach() * mask).clone()
        gp = torch.zeros(7, dtype=torch.float64, requires_grad=True)
        soft.energy(gp * mask).backward()
        directions = [step, -(gp.grad * mask)]
        taken, motion = False, 0.0
        for d in directions:
            if not torch.isfinite(d).all() or not d.abs().max() > 0:
                continue
            m = soft.max_motion(d)
            limit = step_px if d is step else 0.5 * step_px
            if m > limit:
                d, m = d * (limit / m), limit
            for _ in range(4):  # the exact render decides; halve the step until it helps
                cand = apply_update(camera, d.numpy())
                cv_ = _render(renderer, cand, q, lv, cfg)
                fit.renders += 1
                if cv_.energy <= v.energy:
                    camera, v, taken, motion = cand, cv_, True, m
                    fit.update = fit.update + d.numpy()
                    break
                d, m = d * 0.5, m * 0.5
            if taken:
                break
        fit.history.append({"level": lv.scale, "iteration": it, "energy": v.energy, "iou": v.iou,
                            "edge_px": v.edge, "motion_px": motion, "taken": taken})
        if log:
            log(f"  level {lv.scale:g} it {it}: E={v.energy:.5f} IoU={v.iou:.4f} edge={v.edge:.3f} "
                f"step={motion:.3f}px")
        if not taken or motion < cfg.tolerance_px:
            break
    return camera


def _derivative_free_level(renderer, camera: Camera, q: torch.Tensor, lv: _Level, cfg: RefineConfig,
                           fit: CameraFit, level_index: int, log: Callable[[str], None] | None) -> Camera:
    from scipy.optimize import minimize

    n_par = 7 if cfg.refine_focal else 6
    # initial search size: a few level pixels of image motion (coarse levels search wider)
    px = 1.0 / lv.scale
    size = 0.5 * px * (2.0 if level_index == 0 else 1.0)
    start = camera

    def energy(x):
        fit.renders += 1
        return _render(renderer, apply_update(start, x), q, lv, cfg).energy

    x0 = np.zeros(n_par)
    evals = cfg.max_iterations * 10
    if cfg.method == "nelder-mead":
        simplex = np.vstack([x0, np.diag(np.full(n_par, size))])
        res = minimize(energy, x0, method="Nelder-Mead",
                       options={"initial_simplex": simplex, "maxfev": evals, "xatol": 1e-3, "fatol": 1e-7})
    else:
        res = minimize(energy, x0, method="Powell",
                       options={"maxfev": evals, "xtol": 1e-3, "ftol": 1e-7, "direc": np.eye(n_par) * size})
    step = np.zeros(7)
    step[:n_par] = res.x
    base = energy(x0)
    if res.fun <= base:
        camera = apply_update(start, step)
        fit.update = fit.update + step
    fit.history.append({"level": lv.scale, "iteration": int(res.nfev), "energy": float(min(res.fun, base)),
                        "taken": bool(res.fun <= base)})
    if log:
        log(f"  level {lv.scale:g}: {cfg.method} {res.nfev} evaluations, E={min(res.fun, base):.5f}")
    return camera


# ----------------------------------------------------------------------------- refine


def refine_camera(renderer, camera: Camera, q, target: np.ndarray, config: RefineConfig = RefineConfig(),
                  *, edges: bool = False, log: Callable[[str], None] | None = None) -> CameraFit:
    """Refine one camera's pose (and optionally focal length) so the rendered robot matches
    ``target``.

    ``renderer``: an :class:`imac_data.render.Renderer` of the robot; ``camera``: the initial
    calibration (any resolution; it is rescaled to the frames'); ``q`` ``(N, D)`` the frames'
    joint vectors; ``target`` ``(N, H, W)`` the robot pixels of those frames (bool, or a
    probability in [0, 1]), or with ``edges=True`` the frames' image edges near the robot
    (:func:`image_edges`; the rendered outline is pulled onto the nearest edge, no IoU term).
    Returns a :class:`CameraFit` whose ``camera`` has ``camera``'s resolution.
    """
    target = np.asarray(target)
    if target.ndim != 3:
        raise InputError(f"refine_camera: target must be (N, H, W), got shape {target.shape}")
    q = torch.as_tensor(np.asarray(q, dtype=np.float64))
    if q.ndim != 2 or len(q) != len(target):
        raise InputError(f"refine_camera: q must be (N, D) with N = {len(target)} frames, got {tuple(q.shape)}")
    if target.dtype == bool:
        target = target.astype(np.float32)
    if not np.isfinite(target).all() or target.min() < 0 or target.max() > 1:
        raise InputError("refine_camera: target must hold robot probabilities in [0, 1]")
    H, W = target.shape[1:]
    if edges:
        config = dataclasses.replace(config, iou_weight=0.0, edge_weight=config.edge_weight or 1.0)
    t0, c0 = time.perf_counter(), time.process_time()
    cam = camera if (camera.height, camera.width) == (H, W) else camera.rescaled(W, H)
    fit = CameraFit(camera=cam, initial=camera, update=np.zeros(7))
    levels = [s for s in config.levels if round(W * s) >= config.min_level_width] or [config.levels[-1]]
    for i, s in enumerate(levels):
        lv = _make_level(cam, target, s, config.pad, edges)
        if config.method == "gradient":
            cam = _gradient_level(renderer, cam, q, lv, config, config.step_px if i == 0 else config.fine_step_px,
                                  fit, log)
        else:
            cam = _derivative_free_level(renderer, cam, q, lv, config, fit, i, log)
    fit.camera = cam if (cam.height, cam.width) == (camera.height, camera.width) else \
        cam.rescaled(camera.width, camera.height)
    fit.wall_s = time.perf_counter() - t0
    fit.cpu_s = time.process_time() - c0
    return fit


# ----------------------------------------------------------------------------- edge cue


def image_edges(images: np.ndarray, rendered: np.ndarray, *, margin_px: int, low: float = 20.0,
                high: float = 60.0) -> np.ndarray:
    """The built-in robot cue: image edges ``(N, H, W)`` bool near the robot as the current
    calibration renders it.

    ``images`` ``(N, H, W, 3)`` uint8; ``rendered`` ``(N, H, W)`` the robot rendered with the
    current calibration, off by up to about ``margin_px``. Canny edges (hysteresis thresholds
    ``low``, ``high`` on 8-bit intensity steps) of each colour channel, combined, kept within
    ``margin_px`` of the rendered robot: the robot's outline is among them, most of the
    scene's clutter is not. A colour model of the robot learnt from the overlay was tried
    first and dropped: simulated table shading alone made it label the table as robot.
    """
    images = np.asarray(images)
    rendered = np.asarray(rendered, dtype=bool)
    if images.ndim != 4 or images.shape[:3] != rendered.shape or images.shape[-1] != 3 or images.dtype != np.uint8:
        raise InputError(f"image_edges: images must be (N, H, W, 3) uint8 matching the masks "
                         f"{rendered.shape}, got {images.shape} {images.dtype}")
    if rendered.sum() < 50:
        raise InputError(f"the current calibration renders almost no robot ({int(rendered.sum())} pixels over "
                         f"{len(rendered)} frames): the edge cue looks for the robot's outline near the current "
                         "overlay, so the calibration must be roughly right (check it with `qa overlay`), or "
                         "give the robot's pixels as masks")
    margin_px = max(1, int(margin_px))
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * margin_px + 1, 2 * margin_px + 1))
    out = np.zeros(rendered.shape, dtype=bool)
    for img, m, o in zip(images, rendered, out):
        e = np.zeros(m.shape, np.uint8)
        for ch in cv2.split(cv2.GaussianBlur(img, (3, 3), 0)):
            e |= cv2.Canny(ch, low, high, L2gradient=True)
        near = cv2.dilate(m.astype(np.uint8), k) > 0
        np.logical_and(e > 0, near, out=o)
    return out
