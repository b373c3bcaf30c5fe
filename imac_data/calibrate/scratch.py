"""One camera calibrated from nothing: its pose (fixed camera) or mount (wrist camera), its
focal length and the depth's scale, from depth and joint states alone, with a confidence and
a refusal when the answer is not unique.

* Fixed camera (:func:`solve_fixed`): the pixels nearer than the static background are the
  moving arm (:func:`~.surface.moving_pixels`); their points, over several frames with the arm
  in different places, are registered to the robot's surface at the recorded joint states
  (global FPFH + RANSAC candidates, then one robust fit over all frames: :mod:`.register`).
* Wrist camera (:func:`solve_mounted`): each frame's whole depth cloud must land, through
  ``FK(q_i)[link] @ T_link_cam``, on the world as the calibrated fixed camera saw it at the same
  instant plus the robot's surface at ``q_i``: a hand-eye problem solved jointly over frames,
  from per-frame global candidates.

A result is refused (:class:`CalibrationRefused`, naming the camera and the reason) when the
inputs cannot pin it down (robot too small in view, too few distinct arm poses) or when it is
ambiguous: a second, different pose explains the depth nearly as well, or the best explains it
poorly. A wrong calibration that looks confident is the outcome this module exists to avoid.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import cv2
import numpy as np

from imac_data.calibrate.register import Fit, Target, evaluate_pose, fit_pose, fpfh_candidates, score_pose
from imac_data.calibrate.surface import RobotSurface, camera_points, lift, moving_pixels, static_background, voxel_thin
from imac_data.errors import InputError

__all__ = ["CalibrationRefused", "ScratchConfig", "CameraResult", "check_poses", "solve_fixed", "solve_mounted",
           "pose_distance"]


class CalibrationRefused(InputError):
    """A camera the command will not write, with the camera and the reason in the message.
    ``fit``/``result``: for a refusal because the best pose explains the depth poorly, that pose (a
    :class:`~.register.Fit`, and as a :class:`CameraResult` with its problem once the solver adds it),
    so that the caller can ask whether a time offset explains the depth (:mod:`.time_offset`)."""

    fit: Fit | None = None
    result: CameraResult | None = None

    @classmethod
    def poor_fit(cls, fit: Fit, message: str) -> CalibrationRefused:
        e = cls(message)
        e.fit = fit
        return e


@dataclass(frozen=True)
class ScratchConfig:
    """How a camera is found from nothing (validated on construction)."""

    frames: int = 10  # frames registered together
    min_separation: float = 0.3  # distance between two distinct arm poses (radians, after the joint map)
    min_coverage: float = 0.01  # the robot's share of the view (depth-moving pixels) to count a frame
    points_per_frame: int = 4000  # observed points kept per frame (voxel-thinned, then subsampled)
    voxel: float = 0.015  # FPFH/RANSAC voxel (metres)
    ransac_runs: int = 6
    depth_margin: float = 0.03  # a pixel is nearer than the background by this fraction of its depth
    min_inlier_ratio: float = 0.8  # below: refused (the best pose explains too little of the depth)
    max_residual_mm: float = 6.0  # above: refused
    ambiguity_ratio: float = 0.9  # a different pose scoring this close to the best: refused
    distinct_mm: float = 20.0  # two poses this far apart (or distinct_deg) are different answers
    distinct_deg: float = 2.0
    focal_range: float = 0.25  # unknown focal: searched over nominal * (1 +- focal_range)
    mount_radius: float = 0.3  # a wrist camera's centre lies within this of its link's origin (metres)

    def __post_init__(self) -> None:
        for name in ("frames", "points_per_frame", "ransac_runs"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < (3 if name == "frames" else 1):
                raise InputError(f"ScratchConfig.{name}: must be an integer >= {3 if name == 'frames' else 1}, got {v!r}")
        for name in ("min_separation", "voxel", "depth_margin", "max_residual_mm", "distinct_mm", "distinct_deg",
                     "mount_radius", "min_coverage"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise InputError(f"ScratchConfig.{name}: must be a finite number > 0, got {v!r}")
        for name in ("min_inlier_ratio", "ambiguity_ratio", "focal_range"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and 0 <= v < 1):
                raise InputError(f"ScratchConfig.{name}: must be in [0, 1), got {v!r}")


@dataclass
class CameraResult:
    """One camera's answer: the pose (``T_world_cam`` or ``T_link_cam``), focal, depth scale and
    the confidence figures of ``report.json``."""

    name: str
    X: np.ndarray
    focal: float
    scale: float
    confidence: dict = field(default_factory=dict)
    frames: list = field(default_factory=list)  # indices into the candidate frames
    problem: tuple = ()  # (obs, A, targets): what the depth fit was, to judge another pose on it

    def depth_agreement(self, X: np.ndarray, cut: float = 0.008) -> tuple[float, float]:
        """(inlier share, RMS mm) of the depth fit at another pose ``X`` (same focal and scale)."""
        obs, A, targets = self.problem
        return evaluate_pose(obs, A, X, targets, self.focal, self.scale, cut)


def pose_distance(A: np.ndarray, B: np.ndarray) -> tuple[float, float]:
    """(translation mm, rotation degrees) between two 4x4 poses."""
    D = np.linalg.inv(A) @ B
    ang = math.degrees(math.acos(np.clip((np.trace(D[:3, :3]) - 1) / 2, -1, 1)))
    return float(np.linalg.norm(A[:3, 3] - B[:3, 3]) * 1e3), ang


def check_poses(camera: str, q: np.ndarray, config: ScratchConfig) -> None:
    """Refuse before any work when the joint states hold too few distinct arm poses. ``q``: the frames'
    configurations, joint vectors through the robot's joint map (radians, metres:
    :meth:`~imac_data.core.robot.model.RobotModel.mapped_joints`)."""
    q = np.asarray(q, dtype=np.float64)
    chosen = [0]
    dist = np.linalg.norm(q - q[0], axis=1)
    while len(chosen) < 3:
        k = int(np.argmax(dist))
        if dist[k] < config.min_separation:
            break
        chosen.append(k)
        dist = np.minimum(dist, np.linalg.norm(q - q[k], axis=1))
    if len(chosen) < 3:
        raise CalibrationRefused(
            f"camera {camera!r}: too few distinct arm poses: the frames hold {len(chosen)} joint configuration(s) "
            f"at least {config.min_separation} rad apart, and a pose from depth needs the arm in at least 3 different "
            "places (more is better). Use episodes where the arm moves, or more episodes")


def _spread(q: np.ndarray, score: np.ndarray, count: int, min_sep: float) -> np.ndarray:
    """Farthest-point choice of up to ``count`` frames (sorted indices) among configurations ``q``, starting at
    the best-scoring frame; frames scoring 0 or less are not chosen, nor a frame closer than ``min_sep`` to a
    chosen one. ``q``: joint vectors through the robot's joint map
    (:meth:`~imac_data.core.robot.model.RobotModel.mapped_joints`, radians, metres), so that the frames chosen do
    not depend on the units the joints were recorded in (degrees or LeRobot's -100..100 would weigh the joints
    differently, and ``min_sep`` would mean another distance in each)."""
    chosen = [int(np.argmax(score))]
    dist = np.linalg.norm(q - q[chosen[0]], axis=1)
    dist[score <= 0] = -1
    while len(chosen) < count:
        k = int(np.argmax(dist))
        if dist[k] < min_sep:
            break
        chosen.append(k)
        dist = np.minimum(dist, np.linalg.norm(q - q[k], axis=1))
    return np.sort(np.array(chosen))


def _thin(obs: np.ndarray, focal: float, config: ScratchConfig, rng) -> np.ndarray:
    keep = obs[voxel_thin(lift(obs, focal), config.voxel / 3)]
    if len(keep) > config.points_per_frame:
        keep = keep[rng.choice(len(keep), config.points_per_frame, replace=False)]
    return keep


def _judge(camera: str, fits: list[Fit], config: ScratchConfig) -> tuple[Fit, dict]:
    """The best fit, and a refusal when a different pose scores nearly as well or the best is poor."""
    fits = sorted(fits, key=lambda f: -f.inlier_ratio)
    best = fits[0]
    rival = next((f for f in fits[1:] if any(a > b for a, b in zip(pose_distance(best.X, f.X),
                                                                        (config.distinct_mm, config.distinct_deg)))),
                 None)
    conf = {"inlier_ratio": best.inlier_ratio, "residual_mm": best.residual_mm,
            "runner_up_inlier_ratio": rival.inlier_ratio if rival else None, "candidates": len(fits)}
    if best.inlier_ratio < config.min_inlier_ratio or best.residual_mm > config.max_residual_mm:
        raise CalibrationRefused.poor_fit(best, 
            f"camera {camera!r}: no pose explains the depth (best: {100 * best.inlier_ratio:.0f}% of the points within "
            f"reach of the robot, residual {best.residual_mm:.1f} mm; needs {100 * config.min_inlier_ratio:.0f}% and "
            f"<= {config.max_residual_mm} mm). Check the joint map, the depth's units, and that the camera sees the arm")
    if rival is not None and rival.inlier_ratio >= config.ambiguity_ratio * best.inlier_ratio:
        t, r = pose_distance(best.X, rival.X)
        raise CalibrationRefused(
            f"camera {camera!r}: ambiguous: two poses {t:.0f} mm and {r:.1f} deg apart explain the depth about equally "
            f"well ({100 * best.inlier_ratio:.0f}% vs {100 * rival.inlier_ratio:.0f}% inliers). Most often the robot "
            "is posed wrongly: check the joint map first, its joints in the order of the dataset's joint vector and "
            "each in the unit it was recorded in (`imac robot joints URDF` prints the joints in chain order; "
            "`--lerobot-robot TYPE` prints a LeRobot arm's map in its units). If the joint map is right, use frames "
            "where more of the arm moves through the view, or give a rough start to `imac qa refine`")
    return best, conf


def solve_fixed(camera: str, q: np.ndarray, depth: np.ndarray, focal: float, principal: tuple[float, float],
                surface: RobotSurface, config: ScratchConfig, *, focal_known: bool, scale_known: bool,
                log=None) -> CameraResult:
    """A fixed camera's ``T_world_cam`` from candidate frames: joint vectors ``q`` ``(M, D)`` and
    depth ``(M, H, W)`` metres (0 = invalid). ``focal``: the recorded or nominal focal length (px)."""
    log = log or (lambda m: None)
    t0 = time.perf_counter()
    poses = surface.robot.mapped_joints(q)  # distances between poses in radians, whatever the recorded units
    check_poses(camera, poses, config)
    bg = static_background(depth)
    moving = moving_pixels(depth, bg, config.depth_margin)
    kernel = np.ones((3, 3), np.uint8)
    moving = np.stack([cv2.morphologyEx(m.astype(np.uint8), cv2.MORPH_OPEN, kernel) > 0 for m in moving])
    coverage = moving.mean(axis=(1, 2))
    usable = coverage >= config.min_coverage
    if not usable.any():
        raise CalibrationRefused(
            f"camera {camera!r}: robot too small in view: in none of the {len(q)} frames does the moving arm cover "
            f"{100 * config.min_coverage:.0f}% of the image in depth (at most {100 * coverage.max():.2f}%). Use a camera "
            "that sees the arm, or frames where it moves in front of the camera")
    sel = _spread(poses, np.where(usable, coverage, 0.0), config.frames, config.min_separation)
    if len(sel) < 3:
        raise CalibrationRefused(
            f"camera {camera!r}: too few distinct arm poses in view: {len(sel)} frame(s) show the arm (>= "
            f"{100 * config.min_coverage:.0f}% of the image) in configurations {config.min_separation} rad apart; needs 3")
    rng = np.random.default_rng(0)
    obs = [_thin(camera_points(depth[i], moving[i], principal), focal, config, rng) for i in sel]
    # every link is a target (a link that moves little still shows as moving pixels), but only the links that
    # move are matched globally: the static base is never among the moving pixels, and would only add clutter
    posed = surface.posed(q[sel])
    targets = [Target(p, n) for p, n in posed]
    A = np.repeat(np.eye(4)[None], len(sel), axis=0)
    src = np.concatenate([lift(o, focal) for o in obs])
    moving_links = np.isin(surface.link, surface.moving_links(q[sel]))
    dst = np.concatenate([p[moving_links] for p, _ in posed])
    dst = dst[voxel_thin(dst, config.voxel / 2)]
    scaling = not (focal_known and scale_known)
    cands = fpfh_candidates(src, dst, config.voxel, with_scaling=scaling, runs=config.ransac_runs)
    # each of the best-covered frames alone too: its correspondences cannot mix arm poses
    for k in np.argsort(-coverage[sel])[:4]:
        cands += fpfh_candidates(lift(obs[k], focal), posed[k][0][moving_links], 0.7 * config.voxel,
                                 with_scaling=scaling, runs=2, seed=100 + int(k))
    log(f"[calibrate] {camera}: {len(sel)} frames, {len(src)} points, {len(cands)} global candidates")
    starts = [_start(T, focal, focal_known, scale_known) for T in cands]
    starts.sort(key=lambda x: -score_pose(obs, A, x[0], targets, x[1], x[2], 0.02))
    fits = [fit_pose(obs, A, X, targets, f0, scale0=s0, free_focal=not focal_known, free_scale=not scale_known,
                     schedule=(0.05, 0.03), iterations=8) for X, f0, s0 in starts[:6]]
    if not fits:
        raise CalibrationRefused(f"camera {camera!r}: global registration found no candidate pose")
    fit, conf = _converge_or_keep(camera, fits, obs, A, targets, focal_known, scale_known, config, sel)
    conf.update(inlier_ratio=fit.inlier_ratio, residual_mm=fit.residual_mm, wall_s=time.perf_counter() - t0,
                coverage=float(coverage[sel].mean()))
    return CameraResult(camera, fit.X, fit.focal, fit.scale, conf, sel.tolist(), (obs, A, targets))


def _start(T: np.ndarray, focal: float, focal_known: bool, scale_known: bool) -> tuple[np.ndarray, float, float]:
    """A similarity from global registration as a start: (pose, focal, depth scale). Its scale is
    the depth's when that is unknown, else the focal length's error (lateral size ~ 1 / focal)."""
    s = float(np.cbrt(np.linalg.det(T[:3, :3])))
    X = np.eye(4)
    X[:3, :3], X[:3, 3] = T[:3, :3] / s, T[:3, 3]
    if not scale_known:
        return X, focal, s
    return X, (focal if focal_known else focal / s), 1.0


def _converge(camera, coarse: list[Fit], obs, A, targets, focal_known: bool, scale_known: bool,
              config: ScratchConfig) -> tuple[Fit, dict]:
    """Run the distinct coarse candidates (best three) to convergence, then judge them: two
    coarse fits a few centimetres apart often reach the same optimum, two converged ones do not."""
    full = [fit_pose(obs, A, f.X, targets, f.focal, scale0=f.scale, free_focal=not focal_known,
                     free_scale=not scale_known) for f in _dedupe(coarse, config)[:3]]
    return _judge(camera, _dedupe(full, config), config)


def _converge_or_keep(camera, coarse, obs, A, targets, focal_known, scale_known, config, sel) -> tuple[Fit, dict]:
    """:func:`_converge`; a refusal for a poor fit carries that fit as a :class:`CameraResult` with its problem."""
    try:
        return _converge(camera, coarse, obs, A, targets, focal_known, scale_known, config)
    except CalibrationRefused as e:
        if e.fit is not None:
            e.result = CameraResult(camera, e.fit.X, e.fit.focal, e.fit.scale,
                                    {"inlier_ratio": e.fit.inlier_ratio, "residual_mm": e.fit.residual_mm},
                                    np.asarray(sel).tolist(), (obs, A, targets))
        raise


def _dedupe(fits: list[Fit], config: ScratchConfig) -> list[Fit]:
    """Keep one fit per distinct pose (the best of each cluster)."""
    out: list[Fit] = []
    for f in sorted(fits, key=lambda f: -f.inlier_ratio):
        if all(any(a > b for a, b in zip(pose_distance(f.X, g.X), (config.distinct_mm, config.distinct_deg)))
               for g in out):
            out.append(f)
    return out


def solve_mounted(camera: str, q: np.ndarray, depth: np.ndarray, link_poses: np.ndarray, scene,
                  focal: float, principal: tuple[float, float], config: ScratchConfig, *, robot, focal_known: bool,
                  scale_known: bool, log=None) -> CameraResult:
    """A wrist camera's mount ``T_link_cam`` from candidate frames: ``q`` ``(M, D)``, depth
    ``(M, H, W)``, ``link_poses`` ``(M, 4, 4)`` (FK of its link), ``scene(i)``: the
    :class:`~.register.Target` world at candidate frame i (fixed cameras' depth and the robot's
    surface) to register to; ``robot``: its joint map measures how far apart the frames' poses are."""
    log = log or (lambda m: None)
    t0 = time.perf_counter()
    poses = robot.mapped_joints(q)
    check_poses(camera, poses, config)
    valid = (depth > 0).mean(axis=(1, 2))
    sel = _spread(poses, valid, config.frames, config.min_separation)
    if len(sel) < 3:
        raise CalibrationRefused(f"camera {camera!r}: too few distinct arm poses with depth: {len(sel)} (needs 3)")
    rng = np.random.default_rng(0)
    full = np.ones(depth.shape[1:], bool)
    obs = [_thin(camera_points(depth[i], full, principal), focal, config, rng) for i in sel]
    A = link_poses[sel]
    targets = [scene(int(i)) for i in sel]
    cands = []
    for k, i in enumerate(sel):  # each frame alone: candidate mounts
        src = lift(obs[k], focal)
        tg = targets[k].points
        near = tg[np.linalg.norm(tg - A[k][:3, 3], axis=1) < 1.5]  # what a wrist camera can see
        for T in fpfh_candidates(src, near, config.voxel, with_scaling=not scale_known, runs=2, seed=int(i)):
            s = float(np.cbrt(np.linalg.det(T[:3, :3])))
            W = np.eye(4)
            W[:3, :3], W[:3, 3] = T[:3, :3] / s, T[:3, 3]
            X = np.linalg.inv(A[k]) @ W
            if np.linalg.norm(X[:3, 3]) <= config.mount_radius:
                cands.append((X, s))
    log(f"[calibrate] {camera}: {len(sel)} frames, {len(cands)} mount candidates within {config.mount_radius} m")
    if not cands:
        raise CalibrationRefused(
            f"camera {camera!r}: no frame's depth could be placed in the scene with a mount within "
            f"{config.mount_radius} m of its link; check the link name and that the fixed cameras see the scene")
    scored = sorted(cands, key=lambda c: -score_pose(obs, A, c[0], targets, focal, c[1] if not scale_known else 1.0,
                                                     0.02))
    fits = [fit_pose(obs, A, X, targets, focal, scale0=s if not scale_known else 1.0, free_focal=not focal_known,
                     free_scale=not scale_known, schedule=(0.05, 0.03), iterations=8) for X, s in scored[:6]]
    fit, conf = _converge_or_keep(camera, fits, obs, A, targets, focal_known, scale_known, config, sel)
    conf.update(inlier_ratio=fit.inlier_ratio, residual_mm=fit.residual_mm, wall_s=time.perf_counter() - t0)
    return CameraResult(camera, fit.X, fit.focal, fit.scale, conf, sel.tolist(), (obs, A, targets))
