"""``qa calibrate``: a whole calibration from a recording that comes with none.

Inputs: the recording (raw HDF5 episodes or a LeRobot dataset), the robot (URDF and joint map,
from a recipe), depth (recorded, or Depth Anything 3's monocular model, whose scale is then
estimated), the image size, and for each camera its recorded intrinsics or a nominal field of
view. Fixed cameras are found first (:func:`~.scratch.solve_fixed`), then each wrist camera's
mount against the world the fixed cameras saw (:func:`~.scratch.solve_mounted`). The result
goes to the existing refinement (``qa refine``, edge cue), whose pose is kept only where it
agrees with the depth. A camera that cannot be pinned down is refused, by name and reason, and
not written. ``docs/calibration.md`` ("No calibration at all") has the method and the figures.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import shutil
import sys
import tempfile
import time
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import open3d as o3d
import torch
from tqdm import tqdm

from imac_data.calibrate.frames import DatasetFrames, open_frames
from imac_data.calibrate.refine import _check_outputs, refine_calibration
from imac_data.calibrate.register import Target, fit_pose
from imac_data.calibrate.scratch import (
    CalibrationRefused,
    CameraResult,
    ScratchConfig,
    pose_distance,
    solve_fixed,
    solve_mounted,
)
from imac_data.calibrate.surface import RobotSurface, lift
from imac_data.calibrate.time_offset import OffsetSearch, episode_joints_at, search_offset, timing_refusal
from imac_data.core.cameras import Camera, intrinsics_from_fovy, load_calibration, save_calibration
from imac_data.core.rig import Rig
from imac_data.core.robot.joint_ranges import joint_range_warning
from imac_data.errors import InputError
from imac_data.recipes import load_recipe
from imac_data.sources.da3 import DEFAULT_DA3_METRIC_MODEL, DepthAnything3Metric
from imac_data.sources.hdf5 import EpisodeReader

__all__ = ["DEPTH_KINDS", "FOV_SWEEP", "NO_DEPTH_HELP", "calibrate_from_nothing", "format_calibration_report"]

DEPTH_KINDS = ("recorded", "da3")
NO_DEPTH_HELP = ("calibration from nothing registers depth to the robot: record depth, or estimate it with Depth "
                 "Anything 3 (`--depth da3 --da3-model DIR`, its monocular model; the scale is estimated with the "
                 "pose), or give a rough starting pose (a few cm and degrees) to `imac qa refine` instead")


CALIBRATE_GOES_ON = ("Calibration goes on with the joints as recorded: a robot posed wrongly fits no camera, so fix the "
                     "joint map before reading a refusal or a poor fit below as a camera problem.")

# Without a nominal field of view, these are tried in turn: each one's fit starts from focal lengths
# 30 % too short to 50 % too long (measured, docs/calibration.md), so together they cover about 17-110 deg.
FOV_SWEEP = (25.0, 50.0, 90.0)
# A fitted focal length more than this many times off its start is no lens the start could stand for: the sweep's
# starts are 1.8 times apart, a nominal field of view is within tens of percent. A robot posed wrongly (joint values
# in other units than the joint map's) is what such a fit explains (docs/calibration.md, "Refusals").
FOCAL_SPAN = 2.0


def _intrinsics(cams, hw, intrinsics: Path | None, fov: Mapping[str, float]) -> dict[str, tuple[list, str]]:
    """Per camera: (the K to start from at the images' size, where they come from: ``recorded``,
    ``nominal`` or ``sweep``). Recorded intrinsics are used as they are; a nominal vertical field
    of view, or else :data:`FOV_SWEEP`, gives a focal length to be estimated at the image centre."""
    recorded = load_calibration(intrinsics) if intrinsics is not None else {}
    out = {}
    for c in cams:
        H, W = hw[c]
        if c in recorded:
            out[c] = ([recorded[c].for_images(H, W, where=f"{c} images").K], "recorded")
        elif c in fov or "*" in fov:
            deg = fov.get(c, fov.get("*"))
            if not (isinstance(deg, (int, float)) and 1.0 <= deg <= 170.0):
                raise InputError(f"--fov for camera {c!r}: a vertical field of view in degrees in [1, 170], got {deg!r}")
            out[c] = ([intrinsics_from_fovy(float(deg), W, H)], "nominal")
        else:
            out[c] = ([intrinsics_from_fovy(d, W, H) for d in FOV_SWEEP], "sweep")
    return out


RESOLVE_ROUNDS = 3  # solves at an offset for a camera refused in step (each from the last one's best poor pose)


def _candidates(lengths: Mapping[str, int], budget: int) -> list[tuple[str, int]]:
    """About ``budget`` frames spread evenly over every episode (``lengths``: episode -> frames)."""
    total = sum(lengths.values())
    step = max(1, math.ceil(total / budget))
    return [(ep, t) for ep in lengths for t in range(0, lengths[ep], step)]


def _recorded_depth(frames, cam: str, refs) -> np.ndarray | None:
    """Recorded depth (metres, 0 = invalid) of ``cam`` at ``refs``, or None without any."""
    if isinstance(frames, DatasetFrames):  # the dataset's own depth stream, if it has one
        eps = dict.fromkeys(e for e, _ in refs)
        parts = [frames.depth_metres(ep, cam, [t for e, t in refs if e == ep]) for ep in eps]
        return None if any(p is None for p in parts) else np.concatenate(parts)
    out = []
    for ep in dict.fromkeys(e for e, _ in refs):
        ts = [t for e, t in refs if e == ep]
        with EpisodeReader(ep, cameras=[cam]) as r:
            if cam not in r.depth_cameras:
                return None
            out += [np.asarray(r.depth_mm(cam, t, t + 1)[0], dtype=np.float32) / 1000.0 for t in ts]
    return np.stack(out)


def _da3_depth(model, frames, cam: str, refs, K: np.ndarray) -> np.ndarray:
    """Depth Anything 3 in its pose-free mode: the scale follows the focal guess and is estimated later."""
    images = np.concatenate([frames.images(ep, cam, [t for e, t in refs if e == ep])
                             for ep in dict.fromkeys(e for e, _ in refs)])
    return model.predict_pose_free(images, float(K[0, 0]), where=f"{frames.source} camera {cam!r}")


class _Scene:
    """The world at candidate frame i, as the calibrated fixed cameras saw it (their whole depth,
    normals estimated, cached per frame) plus the robot's surface at a joint vector: what a wrist
    camera's depth must land on. ``at(q)``: ``scene(i)`` with the robot at ``q[i]``."""

    def __init__(self, fixed: dict[str, CameraResult], depth: dict, principal: dict, surface: RobotSurface):
        self.fixed, self.depth, self.principal, self.surface = fixed, depth, principal, surface
        self._world: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def world(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        if i not in self._world:
            pts, nrm = [], []
            for c, res in self.fixed.items():
                d = self.depth[c][i]
                v, u = np.nonzero(d > 0)
                obs = np.stack([u - self.principal[c][0], v - self.principal[c][1], d[v, u]], axis=1)
                p = lift(obs, res.focal, res.scale) @ res.X[:3, :3].T + res.X[:3, 3]
                pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p)).voxel_down_sample(0.003)
                pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=0.02, max_nn=30))
                pts.append(np.asarray(pcd.points))
                nrm.append(np.asarray(pcd.normals))
            self._world[i] = (np.concatenate(pts), np.concatenate(nrm))
        return self._world[i]

    def target(self, i: int, q: np.ndarray) -> Target:
        rp, rn = self.surface.posed(np.asarray(q)[None])[0]
        p, n = self.world(i)
        return Target(np.concatenate([p, rp]), np.concatenate([n, rn]))

    def at(self, q: np.ndarray):
        cache: dict[int, Target] = {}

        def scene(i: int) -> Target:
            if i not in cache:
                cache[i] = self.target(i, q[i])
            return cache[i]

        return scene


def _solve(c: str, starts: list[np.ndarray], focal_known: bool, scale_known: bool, q: np.ndarray, depths: dict,
           principal: dict, results: dict[str, CameraResult], mounts: Mapping[str, str], robot, surface: RobotSurface,
           config: ScratchConfig, log) -> tuple[list[CameraResult], list[str], list[CameraResult]]:
    """Camera ``c`` from each focal start, with the robot at joint vectors ``q`` of the candidate frames:
    (the answers, the refusals' reasons, the poor fits that were refused)."""
    tries, why, poor = [], [], []
    for K in starts:
        try:
            if c not in mounts:
                tries.append(_plausible(c, solve_fixed(c, q, depths[c], K[0, 0], principal[c], surface, config,
                                                       focal_known=focal_known, scale_known=scale_known, log=log),
                                        K[0, 0], principal[c]))
                continue
            fixed = {f: r for f, r in results.items() if f not in mounts}
            if not fixed:
                raise CalibrationRefused(
                    f"camera {c!r}: a wrist camera's mount is found against the scene a fixed camera saw, and no "
                    "fixed camera with depth was calibrated in this run (calibrate one in the same run, or give a "
                    "rough mount to `imac qa refine`)")
            lp = robot.link_poses(torch.as_tensor(q))[mounts[c]].numpy()
            tries.append(_plausible(c, solve_mounted(c, q, depths[c], lp, _Scene(fixed, depths, principal, surface).at(q),
                                                     K[0, 0], principal[c], config, robot=robot,
                                                     focal_known=focal_known, scale_known=scale_known, log=log),
                                        K[0, 0], principal[c]))
        except CalibrationRefused as e:
            why.append(str(e))
            if e.result is not None:
                poor.append(e.result)
    return tries, why, poor


def _plausible(c: str, res: CameraResult, start: float, principal) -> CameraResult:
    """``res``, unless its focal length is more than ``FOCAL_SPAN`` times off its ``start``: refused, the likelier
    cause (the joints' units) first."""
    ratio = res.focal / start
    if 1 / FOCAL_SPAN <= ratio <= FOCAL_SPAN:
        return res
    fov = 2 * np.degrees(np.arctan(principal[1] / res.focal))
    raise CalibrationRefused(
        f"camera {c!r}: the pose that explains the depth best needs a focal length of {res.focal:.0f} px (a {fov:.1f} "
        f"deg field of view), {ratio:.2g} times its start of {start:.0f} px: no camera, but a robot posed wrongly. "
        "Check the joint map's units first (LeRobot records degrees or -100..100 with the robot's calibration file: "
        "`imac robot joints URDF --lerobot-robot TYPE` prints the map), then the depth's units, then --fov")


def _problem_at(c: str, frames: list[int], q_at, mounts: Mapping[str, str], robot, surface: RobotSurface,
                results: dict[str, CameraResult], depths: dict, principal: dict):
    """``offset -> (A, targets)``: camera ``c``'s depth fit on candidate ``frames`` with the robot at the
    joint states of ``t + offset`` (:func:`~.time_offset.search_offset`)."""
    frames = np.asarray(frames)
    scene = _Scene({f: r for f, r in results.items() if f not in mounts}, depths, principal, surface) \
        if c in mounts else None

    def problem(offset: float):
        qd = q_at(offset)[frames]
        if scene is None:
            return np.repeat(np.eye(4)[None], len(frames), axis=0), [Target(p, n) for p, n in surface.posed(qd)]
        A = robot.link_poses(torch.as_tensor(qd))[mounts[c]].numpy()
        return A, [scene.target(int(i), qd[k]) for k, i in enumerate(frames)]

    return problem


def _away_from_ends(res: CameraResult, refs: list[tuple[str, int]], lengths: Mapping[str, int],
                    margin: int) -> CameraResult:
    """``res`` on its frames at least ``margin`` frames from their episode's ends (all of them if fewer than 3
    are): the offset search poses the robot up to ``margin`` frames away, and joint states clamped at an end
    are not what the image shows (an arm moving from the first frame pulled offset and pose off)."""
    keep = [k for k, i in enumerate(res.frames) if margin <= refs[i][1] < lengths[refs[i][0]] - margin]
    if len(keep) == len(res.frames) or len(keep) < 3:
        return res
    obs, A, targets = res.problem
    problem = ([obs[k] for k in keep], np.asarray(A)[keep], [targets[k] for k in keep])
    return dataclasses.replace(res, frames=[res.frames[k] for k in keep], problem=problem)


def _with_offset(res: CameraResult, search: OffsetSearch, problem, focal_known: bool, scale_known: bool) -> CameraResult:
    """``res`` fitted to convergence at the searched offset, from the search's pose there."""
    obs = res.problem[0]
    A, targets = problem(search.offset_s)
    f = search.fit
    fit = fit_pose(obs, A, f.X, targets, f.focal, scale0=f.scale, free_focal=not focal_known,
                   free_scale=not scale_known, schedule=(0.02, 0.012, 0.008))
    conf = dict(res.confidence, inlier_ratio=fit.inlier_ratio, residual_mm=fit.residual_mm)
    return CameraResult(res.name, fit.X, fit.focal, fit.scale, conf, res.frames, (obs, A, targets))


def _pick(camera: str, tries: list[CameraResult], why: list[str], config: ScratchConfig) -> CameraResult:
    """The answer of a camera over its focal starts: the best fit, unless a different pose fits
    about as well (ambiguous); refused with every start's reason when none gave one."""
    if not tries:
        raise CalibrationRefused(why[0] if len(why) == 1 else f"camera {camera!r}: every focal start refused: "
                                 + " | ".join(dict.fromkeys(why)))
    tries = sorted(tries, key=lambda r: -r.confidence["inlier_ratio"])
    best = tries[0]
    for other in tries[1:]:
        t, r = pose_distance(best.X, other.X)
        if (t > config.distinct_mm or r > config.distinct_deg) and \
                other.confidence["inlier_ratio"] >= config.ambiguity_ratio * best.confidence["inlier_ratio"]:
            raise CalibrationRefused(f"camera {camera!r}: ambiguous: focal starts {best.focal:.0f} and "
                                     f"{other.focal:.0f} px lead to poses {t:.0f} mm and {r:.1f} deg apart that fit "
                                     "about equally well; give the nominal field of view (--fov)")
    return best


def _camera(name: str, K: np.ndarray, res: CameraResult, hw, link: str | None) -> Camera:
    K = K.copy()
    K[0, 0] = K[1, 1] = res.focal
    H, W = hw
    offset = float(res.confidence.get("time_offset_s", 0.0))
    if link:
        return Camera(name, K, W, H, link=link, T_link_cam=_rigid(res.X), time_offset_s=offset)
    return Camera(name, K, W, H, T_world_cam=_rigid(res.X), time_offset_s=offset)


def _rigid(X: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(X[:3, :3])
    out = np.eye(4)
    out[:3, :3] = U @ np.diag([1, 1, np.linalg.det(U @ Vt)]) @ Vt
    out[:3, 3] = X[:3, 3]
    return out


def calibrate_from_nothing(source: str | Path, out: str | Path, *, recipe, cameras: Sequence[str] | None = None,
                           mounts: Mapping[str, str] | None = None, fov: Mapping[str, float] | None = None,
                           intrinsics: str | Path | None = None, depth: str = "recorded", da3_model=None,
                           estimate_depth_scale: bool = False,
                           config: ScratchConfig | None = None, candidates: int = 60, refine: str = "edges",
                           near: float = 0.0, report: str | Path | None = None, overwrite: bool = False,
                           time_offset_window: float = 0.2, progress: bool = True, log=None) -> dict:
    """Calibrate every camera of ``source`` from nothing; write ``out`` (the cameras found) and the
    report directory; return the report dict. ``mounts``: camera -> URDF link for wrist cameras;
    ``fov``: camera (or ``"*"``) -> nominal vertical field of view in degrees (none: :data:`FOV_SWEEP`
    is tried); ``intrinsics``: a calibration file whose K are used as recorded;
    ``estimate_depth_scale``: the recorded depth's scale is not trusted and is estimated with the
    pose (always so for Depth Anything 3); ``time_offset_window``: each camera's constant time offset to
    the joint states is searched within +- this many seconds (0: not searched; :mod:`.time_offset`).
    Inputs are checked before any work."""
    log = log or (lambda msg: None)
    config = config or ScratchConfig()
    mounts, fov = dict(mounts or {}), dict(fov or {})
    source, out = Path(source), Path(out)
    report = Path(report) if report is not None else out.with_name(out.stem + ".report")
    if depth not in DEPTH_KINDS:
        raise InputError(f"--depth must be one of {DEPTH_KINDS}, got {depth!r}")
    if refine not in ("edges", "none"):
        raise InputError(f"--refine must be 'edges' or 'none', got {refine!r}")
    if not (math.isfinite(near) and near >= 0):
        raise InputError(f"--near must be >= 0 metres, got {near}")
    if not (math.isfinite(time_offset_window) and 0 <= time_offset_window <= 2.0):
        raise InputError(f"--max-time-offset must be within 0-2000 ms, got {1e3 * time_offset_window:g} ms")
    if candidates < config.frames:
        raise InputError(f"--candidates ({candidates}) must be at least --frames ({config.frames})")
    recipe_path = Path(recipe) if isinstance(recipe, (str, Path)) else (Path(recipe.file) if recipe.file else None)
    intrinsics = Path(intrinsics) if intrinsics is not None else None
    _check_outputs(out, report, {"source": source, "recipe": recipe_path, "intrinsics": intrinsics}, overwrite)
    recipe = load_recipe(recipe) if isinstance(recipe, (str, Path)) else recipe
    robot = Rig.robot_from_recipe(recipe)
    frames = open_frames(source, recipe.depth)
    cams = list(cameras) if cameras else list(frames.cameras)
    missing = [c for c in cams if c not in frames.cameras]
    if missing:
        raise InputError(f"{source}: camera(s) {missing} not in the source (it has {frames.cameras})")
    for c, link in mounts.items():
        if c not in cams:
            raise InputError(f"--mount {c}={link}: camera {c!r} is not among the cameras ({cams})")
        if link not in robot.link_names:
            raise InputError(f"--mount {c}={link}: robot {robot.name!r} has no link {link!r}")
    unmounted = [c for c in cams if "wrist" in c and c not in mounts]
    if unmounted:
        raise InputError(f"camera(s) {unmounted} look like wrist cameras: say which link each is mounted on with "
                         "--mount CAMERA=LINK (or --cameras to leave them out)")
    joints = {ep: frames.joints(ep) for ep in frames.episodes}
    wrong = sorted({q.shape[1] for q in joints.values()} - {robot.dof})
    if wrong:
        raise InputError(f"{source}: joint vectors have {wrong[0]} entries, robot {robot.name!r} expects {robot.dof}")
    # the build's check, before any search: a joint map in the wrong unit poses the robot wrongly, and no camera fits
    recorded = np.concatenate(list(joints.values()))
    if len(recorded):
        warning = joint_range_warning(robot, recorded.min(axis=0), recorded.max(axis=0), source=str(source),
                                      recipe=recipe.file or "the recipe", then=CALIBRATE_GOES_ON)
        if warning:
            print(warning, file=sys.stderr)
    hw = {c: frames.image_hw(c) for c in cams}
    Ks = _intrinsics(cams, hw, intrinsics, fov)
    model = None
    if depth == "da3":
        model = DepthAnything3Metric(da3_model or DEFAULT_DA3_METRIC_MODEL, local_files_only=True)

    lengths = {ep: len(q) for ep, q in joints.items()}
    refs = _candidates(lengths, candidates)
    q = np.concatenate([joints[ep][[t for e, t in refs if e == ep]] for ep in dict.fromkeys(e for e, _ in refs)])
    refused: dict[str, str] = {}
    depths = {}
    for c in cams:  # depth availability is known before any registration
        d = _recorded_depth(frames, c, refs) if depth == "recorded" else None
        if d is None and depth == "recorded":
            refused[c] = f"camera {c!r}: no depth recorded in {source}; {NO_DEPTH_HELP}"
        else:
            depths[c] = d
    if len(refused) == len(cams):
        raise CalibrationRefused("; ".join(refused.values()))

    t0, c0 = time.perf_counter(), time.process_time()
    surface = RobotSurface(robot)
    principal = {c: (Ks[c][0][0][0, 2], Ks[c][0][0][1, 2]) for c in cams}
    results: dict[str, CameraResult] = {}
    order = [c for c in cams if c not in mounts and c in depths] + [c for c in cams if c in mounts and c in depths]
    fps = recipe.fps if recipe.fps is not None else getattr(frames, "fps", None)
    window = float(time_offset_window) if fps else 0.0
    if time_offset_window > 0 and not fps:
        log("[calibrate] the recording's frame rate is unknown (no fps in the recipe or the episodes): the cameras' "
            "time offsets are not searched")
    shifted: dict[float, np.ndarray] = {0.0: q}

    def q_at(offset: float) -> np.ndarray:
        if offset not in shifted:
            shifted[offset] = episode_joints_at(joints, refs, offset * fps)
        return shifted[offset]

    for c in tqdm(order, desc="calibrate", unit="camera", disable=not progress):
        starts, how = Ks[c]
        if depths[c] is None:
            log(f"[calibrate] {c}: Depth Anything 3 on {len(refs)} frames")
            depths[c] = _da3_depth(model, frames, c, refs, starts[0])
        scale_known = depth == "recorded" and not estimate_depth_scale
        focal_known = how == "recorded"
        tc = time.perf_counter()
        common = (depths, principal, results, mounts, robot, surface, config, log)
        tries, why, poor = _solve(c, starts, focal_known, scale_known, q, *common)
        try:
            res, reason = _pick(c, tries, why, config), None
        except CalibrationRefused as e:
            res, reason = None, str(e)
        base = res if res is not None else max(poor, key=lambda r: r.confidence["inlier_ratio"], default=None)
        search = None

        def offset_search(r: CameraResult) -> tuple[OffsetSearch, object, CameraResult]:
            r = _away_from_ends(r, refs, lengths, math.ceil(window * fps - 1e-9))
            problem = _problem_at(c, r.frames, q_at, mounts, robot, surface, results, depths, principal)
            found = search_offset(problem, r.problem[0], r.X, r.focal, r.scale, fps=fps, window_s=window,
                                  free_focal=not focal_known, free_scale=not scale_known)
            log(f"[calibrate] {c}: time offset {1e3 * found.offset_s:+.1f} ms (cost {found.cost:.4f}, at 0 ms "
                f"{found.cost_at_zero:.4f}; {found.rise:+.0%} one frame away; {len(found.curve)} fits on "
                f"{len(r.frames)} frames)")
            return found, problem, r

        if base is not None and window > 0:
            search, problem, searched = offset_search(base)
            if res is not None:
                if search.observable and search.offset_s != 0:
                    res = _with_offset(searched, search, problem, focal_known, scale_known)
            elif search.clearly_better:
                for _ in range(RESOLVE_ROUNDS):  # a better poor pose searches the offset better: alternate
                    log(f"[calibrate] {c}: refused in step with the joint states, but the depth fits "
                        f"{1e3 * search.offset_s:+.0f} ms off far better: solving again there")
                    tries, why, poor = _solve(c, starts, focal_known, scale_known, q_at(search.offset_s), *common)
                    try:
                        res = _pick(c, tries, why, config)
                        break
                    except CalibrationRefused as e:
                        reason = timing_refusal(c, search, str(e))
                    better = max(poor, key=lambda r: r.confidence["inlier_ratio"], default=None)
                    if better is None or better.confidence["inlier_ratio"] <= base.confidence["inlier_ratio"]:
                        break
                    base = better
                    again = offset_search(base)
                    if not again[0].clearly_better:
                        break
                    search, problem, searched = again
                if res is not None:
                    again, problem, searched = offset_search(res)
                    if again.observable:
                        search = again
                        res = _with_offset(searched, search, problem, focal_known, scale_known)
                    else:  # the solve at the estimate stands
                        res.problem = (res.problem[0], *_problem_at(c, res.frames, q_at, mounts, robot, surface,
                                                                    results, depths, principal)(search.offset_s))
        if res is None:
            refused[c] = reason
            log(f"[calibrate] REFUSED {reason}")
            continue
        offset = search.offset_s if search is not None and search.observable else 0.0
        res.confidence.update(wall_s=time.perf_counter() - tc, focal_starts_tried=len(starts))
        res.confidence.update(search.report() if search is not None else {"time_offset_window_s": 0.0})
        res.confidence["time_offset_s"] = offset
        results[c] = res
        log(f"[calibrate] {c}: {100 * res.confidence['inlier_ratio']:.1f}% inliers, residual "
            f"{res.confidence['residual_mm']:.2f} mm, focal {res.focal:.1f} px, depth scale {res.scale:.4f}, "
            f"time offset {1e3 * offset:+.1f} ms")
    if not results:
        raise CalibrationRefused("no camera could be calibrated: " + "; ".join(refused.values()))
    found = {c: _camera(c, Ks[c][0][0], r, hw[c], mounts.get(c)) for c, r in results.items()}
    summary_fps = fps
    summary = {"source": str(source), "out": str(out), "robot": robot.name, "robot_urdf_sha256": robot.urdf_hash,
               "depth": depth, "depth_scale_estimated": depth == "da3" or estimate_depth_scale,
               "config": {k: getattr(config, k) for k in config.__dataclass_fields__},
               "candidate_frames": len(refs), "fps": summary_fps, "time_offset_window_s": window,
               "cameras": {}, "refused": refused,
               "depth_model": model.describe() if model is not None else None}
    for c, r in results.items():
        summary["cameras"][c] = {
            "mounted_on": mounts.get(c), "focal_px": r.focal, "focal_from": Ks[c][1],
            "focal_start_px": [float(K[0, 0]) for K in Ks[c][0]], "depth_scale": r.scale,
            "frames": [list(refs[i]) for i in r.frames],
            **{k: (float(v) if isinstance(v, (float, np.floating)) else v) for k, v in r.confidence.items()}}
    summary["search_wall_s"] = time.perf_counter() - t0
    summary["search_cpu_s"] = time.process_time() - c0
    _finish(source, out, report, recipe, found, results, summary, refine=refine, near=near, log=log)
    return summary


def _finish(source: Path, out: Path, report: Path, recipe, found: dict[str, Camera], results: dict[str, CameraResult],
            summary: dict, *, refine: str, near: float, log) -> None:
    """Hand the depth result to ``qa refine`` (edge cue), keep each refined pose only where the
    depth agrees with it, and write ``out`` and ``report`` (both appear only complete)."""
    out.parent.mkdir(parents=True, exist_ok=True)
    report.parent.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=f".{report.name}.", dir=report.parent))
    try:
        final = dict(found)
        save_calibration(work / "from_depth.json", found)
        if refine == "edges":
            log("[calibrate] handing the calibration to `qa refine` (edge cue)")
            ref = refine_calibration(source, work / "refined.json", recipe=recipe, calibration=work / "from_depth.json",
                                     robot_pixels="edges", cameras=list(found), near=near, report=work / "refine",
                                     log=log)
            refined = load_calibration(work / "refined.json")
            for c, entry in ref["cameras"].items():
                new = refined[c]
                X = new.T_link_cam if new.is_mounted else new.T_world_cam
                ratio, rms = results[c].depth_agreement(X)
                base = results[c].depth_agreement(results[c].X)
                # the silhouette may only move the pose where depth does not object (measured: the edge cue
                # alone lands 2 mm off on the head camera, 12 mm on a wrist; depth fits agree to under 1 mm)
                keep = (not entry["kept_input"]) and rms <= 1.1 * base[1] and ratio >= 0.98 * base[0]
                if keep:
                    final[c] = new
                summary["cameras"][c].update(
                    outline_px_before_refine=entry["boundary_px_before"], outline_px_after_refine=entry["boundary_px_after"],
                    refine_pose_change=entry["pose_change"], refine_accepted=bool(keep),
                    depth_residual_mm_refined=rms, depth_inlier_ratio_refined=ratio)
                for when in ("before", "after"):
                    shutil.copy(work / "refine" / f"{c}_{when}.png", work / f"{c}_{when}_refine.png")
            summary["refine_wall_s"], summary["refine_cpu_s"] = ref["wall_s"], ref["cpu_s"]
        summary["load_avg"] = list(os.getloadavg())
        save_calibration(work / "calibration.json", final)
        load_calibration(work / "calibration.json")  # the calibration parser accepts what we wrote
        (work / "report.json").write_text(json.dumps(summary, indent=2, default=float))
        (work / "refined.json").unlink(missing_ok=True)
        tmp_out = out.with_name(f".{out.name}.tmp")
        shutil.copy(work / "calibration.json", tmp_out)
        if report.exists():
            shutil.rmtree(report)
        work.rename(report)
        tmp_out.replace(out)
    except BaseException:
        shutil.rmtree(work, ignore_errors=True)
        out.with_name(f".{out.name}.tmp").unlink(missing_ok=True)
        raise


def _offset_text(entry: dict) -> str:
    """The time offset column: ms, "?" when the curve had no clear minimum, "-" when not searched."""
    if not entry.get("time_offset_window_s"):
        return "-"
    if not entry.get("time_offset_observable", False):
        return "?"
    return f"{1e3 * entry['time_offset_s']:+.1f}"


def format_calibration_report(summary: dict) -> str:
    """The table ``qa calibrate`` prints, refusals last."""
    lines = [f"wrote {summary['out']} ({len(summary['cameras'])} camera(s)); search {summary['search_wall_s']:.0f} s wall",
             f"{'camera':<18} {'inliers':>8} {'resid mm':>9} {'focal px':>9} {'scale':>7} {'offset ms':>10} "
             f"{'outline px':>11}  refined"]
    for c, e in summary["cameras"].items():
        outline = e.get("outline_px_after_refine")
        lines.append(f"{c:<18} {100 * e['inlier_ratio']:>7.1f}% {e['residual_mm']:>9.2f} {e['focal_px']:>9.1f} "
                     f"{e['depth_scale']:>7.4f} {_offset_text(e):>10} {'-' if outline is None else f'{outline:.2f}':>11}  "
                     f"{'-' if 'refine_accepted' not in e else ('kept' if e['refine_accepted'] else 'rejected by depth')}")
    for c, why in summary["refused"].items():
        lines.append(f"REFUSED {c}: {why}")
    return "\n".join(lines)
