"""The objective of a camera's refinement: how far the rendered robot lies from the robot's
pixels, exactly (at a rendered pose) and differentiably (around it).

The edge term compares distance fields at the rendered silhouette's boundary (robust loss:
occluded or mis-segmented parts stop pulling), the optional soft-IoU term the silhouettes;
both are evaluated coarse to fine with a quadratic B-spline kernel. :func:`silhouette_agreement`
is the report's measure. ``docs/calibration.md`` has the method and its measurements."""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import torch

from imac_data.calibrate.config import RefineConfig
from imac_data.calibrate.pose import UNITS, se3_exp
from imac_data.core.cameras import Camera

__all__ = ["distance_field", "edge_distance", "silhouette_agreement", "Level", "make_level", "level_camera",
           "View", "render_level", "exact_energy", "SoftSilhouette"]

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
class Level:
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


def make_level(camera: Camera, target: np.ndarray, scale: float, pad: float, edges: bool) -> Level:
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
    return Level(scale, h, w, m, t, torch.from_numpy(field.reshape(-1)), _blur(field).reshape(-1),
                  soft, float(np.dot(soft, soft)), edges)


def level_camera(camera: Camera, lv: Level) -> Camera:
    c = camera if (camera.height, camera.width) == (lv.h, lv.w) else camera.rescaled(lv.w, lv.h)
    K = c.K.copy()
    K[0, 2] += lv.m
    K[1, 2] += lv.m
    return Camera(c.name, K, lv.w + 2 * lv.m, lv.h + 2 * lv.m, c.T_world_cam, c.link, c.T_link_cam, c.time_offset_s)


@dataclass
class View:
    """The exact render at one pose (padded) and its objective."""

    mask: np.ndarray  # (N, h + 2m, w + 2m) bool
    depth: np.ndarray
    inside: np.ndarray  # distance of silhouette pixels to the nearest outside pixel
    field: np.ndarray  # blurred distance field of the render
    energy: float = 0.0
    iou: float = 0.0  # soft IoU (binary IoU of the blurred silhouettes' supports is not it)
    edge: float = 0.0  # mean Huber edge residual, px


def render_level(renderer, camera: Camera, q: torch.Tensor, lv: Level, cfg: RefineConfig) -> View:
    out = renderer.render(q, {camera.name: level_camera(camera, lv)})[camera.name]
    mask = out.mask.cpu().numpy()
    inside = np.empty(mask.shape, np.float32)
    for m, o in zip(mask, inside):
        np.copyto(o, cv2.distanceTransform(m.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE))
    v = View(mask, out.depth.cpu().numpy(), inside, _blur(distance_field(mask)))
    v.energy, v.iou, v.edge = exact_energy(v, lv, cfg)
    return v


def _crop(a: np.ndarray, lv: Level) -> np.ndarray:
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


def _contour(v: View, lv: Level) -> np.ndarray:
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


def exact_energy(v: View, lv: Level, cfg: RefineConfig) -> tuple[float, float, float]:
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


class SoftSilhouette:
    """The differentiable objective around one exact render: rendered pixels near the silhouette
    boundary lifted to 3D (rendered z-depth) and moved by the update, splatted over the
    unchanged core of the render; edge pixels sample the target's distance field.

    Only pixels the update can change are tracked (within the trust region's reach of the
    boundary); the rest of the sums are constants, so one evaluation costs O(boundary).
    Heavy arrays are float32 (pixel coordinates to 1e-4 px); the update itself is float64.
    """

    def __init__(self, v: View, camera: Camera, lv: Level, cfg: RefineConfig, step_px: float):
        self.cfg, self.lv, self.refine_focal = cfg, lv, cfg.refine_focal
        reach = step_px + 1.5  # a pixel this deep stays inside after a step (trust region)
        core = v.mask & (v.inside > reach)
        band = v.mask & ~core
        grow = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * int(reach + 2) + 1,) * 2)
        active = _crop(np.stack([cv2.dilate(b.astype(np.uint8), grow) for b in band]) > 0, lv).reshape(-1)
        core_soft = _crop(_blur(core), lv).reshape(-1)
        cam = level_camera(camera, lv)
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
        M = se3_exp(p[:6] * torch.as_tensor(UNITS[:6])).to(X.dtype)
        Xn = (X - M[:3, 3]) @ M[:3, :3]  # M^-1 X, with X as rows
        K = self.K
        s = torch.exp(p[6] * UNITS[6]) if self.refine_focal else torch.ones((), dtype=torch.float64)
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
