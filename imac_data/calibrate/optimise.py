"""The optimisers that move one camera until the objective (:mod:`.objective`) is minimal.

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
``benchmarks/calibration_refine.py`` and summarised in docs/calibration.md.

With the built-in cue (:mod:`.frames`), :func:`refine_camera_edges` repeats
:func:`refine_camera` against the image edges near the overlay, the search margin
shrinking as the overlay improves.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch

from imac_data.calibrate.config import RefineConfig
from imac_data.calibrate.frames import image_edges
from imac_data.calibrate.objective import Level, SoftSilhouette, make_level, render_level
from imac_data.calibrate.pose import apply_update
from imac_data.core.cameras import Camera
from imac_data.errors import InputError

__all__ = ["CameraFit", "refine_camera", "refine_camera_edges"]


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


def _gradient_level(renderer, camera: Camera, q: torch.Tensor, lv: Level, cfg: RefineConfig, step_px: float,
                    fit: CameraFit, log: Callable[[str], None] | None) -> Camera:
    """Iterate: exact render -> soft objective around it -> L-BFGS inside the trust region ->
    the exact render judges the step (halved until it helps; the plain gradient direction as a
    last resort, since far along an L-BFGS direction the landscape can hide a bump)."""
    n_par = 7 if cfg.refine_focal else 6
    v = render_level(renderer, camera, q, lv, cfg)
    fit.renders += 1
    mask = torch.zeros(7, dtype=torch.float64)
    mask[:n_par] = 1.0
    for it in range(cfg.max_iterations):
        soft = SoftSilhouette(v, camera, lv, cfg, step_px)
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
                cv_ = render_level(renderer, cand, q, lv, cfg)
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


def _derivative_free_level(renderer, camera: Camera, q: torch.Tensor, lv: Level, cfg: RefineConfig,
                           fit: CameraFit, level_index: int, log: Callable[[str], None] | None) -> Camera:
    from scipy.optimize import minimize

    n_par = 7 if cfg.refine_focal else 6
    # initial search size: a few level pixels of image motion (coarse levels search wider)
    px = 1.0 / lv.scale
    size = 0.5 * px * (2.0 if level_index == 0 else 1.0)
    start = camera

    def energy(x):
        fit.renders += 1
        return render_level(renderer, apply_update(start, x), q, lv, cfg).energy

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

    ``renderer``: an :class:`imac_data.core.render.Renderer` of the robot; ``camera``: the initial
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
        lv = make_level(cam, target, s, config.pad, edges)
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


def refine_camera_edges(renderer, camera: Camera, q, images: np.ndarray, config: RefineConfig = RefineConfig(), *,
                        rounds: int = 3, margin: float = 0.08, log: Callable[[str], None] | None = None
                        ) -> tuple[CameraFit, np.ndarray]:
    """Refine with the built-in cue: ``rounds`` times, the image edges within ``margin`` (a
    fraction of the image's larger side, halved every round) of the robot as the current
    pose renders it (:func:`image_edges`), then :func:`refine_camera` against them. The
    search margin shrinks as the overlay improves, so scene edges drop out. Returns the
    combined fit and the last round's edge maps ``(N, H, W)``."""
    images = np.asarray(images)
    q = np.asarray(q, dtype=np.float64)
    hw = images.shape[1:3]
    margin_px = max(2, round(margin * max(hw)))
    cam, fits, edges = camera, [], None
    for _ in range(rounds):
        rendered = renderer.render(torch.as_tensor(q), {cam.name: cam}, resolution=hw)[cam.name].mask.numpy()
        edges = image_edges(images, rendered, margin_px=margin_px)
        fits.append(refine_camera(renderer, cam, q, edges, config, edges=True, log=log))
        cam = fits[-1].camera
        margin_px = max(2, margin_px // 2)
    fit = CameraFit(camera=cam, initial=camera, update=sum(f.update for f in fits),
                    history=[h for f in fits for h in f.history], renders=sum(f.renders for f in fits),
                    wall_s=sum(f.wall_s for f in fits), cpu_s=sum(f.cpu_s for f in fits))
    return fit, edges
