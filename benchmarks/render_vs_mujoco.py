"""Motion-image renderer vs MuJoCo: accuracy over whole simulated episodes, and speed.

    python -m benchmarks.render_vs_mujoco [--quick] [--episodes N] [--json PATH]

Accuracy (240x320, both gym-aloha tasks, scripted episodes from
:mod:`imac_data.sources.sim.recorder`, or random workspace configurations if it is missing):

* **robot-only** oracle: MuJoCo renders the frozen-camera model at each recorded
  ``qpos`` with every non-robot geom hidden, i.e. exactly what we render. Mask IoU
  against its segmentation of the robot geoms (bodies under ``vx300s_left`` /
  ``vx300s_right``), and |z-depth error| on pixels both call robot (MuJoCo's
  ``Renderer`` depth is planar z in metres; ``tests/test_render.py`` checks that
  against the table plane). Our renderer gets MuJoCo's near plane
  (``znear * extent`` = 0.166 m) so both clip alike; the table reports how much of
  the robot an unclipped render has in front of that plane.
* **visible** robot: the recorded full-scene segmentation (props and table occlude
  parts of the robot, which a robot-only render cannot know), for reference.

Speed, per view, at 240x320 and 480x640, measured in interleaved blocks of frames
so both sides see the same machine load:

* ours: all three views of a batch of frames (RGB + mask + depth + link ids in one
  pass), and one frame at a time (the online world-model case);
* MuJoCo's own OpenGL renderer (EGL, Mesa on the CPU) on the full scene: RGB pass
  without shadows / multisampling (what our simulator records), depth pass,
  segmentation pass; and the RGB pass with gym-aloha's shipped settings (4096 px
  shadow map, 4x MSAA) on a few frames;
* Open3D with the posed robot's scene rebuilt every frame (the reference timing of docs/verification.md;
  FK + one batched vertex transform + BVH build + casting all views; hit distances
  only, no shading);
* the torch rasteriser (``imac build --device cuda``'s renderer) on the CPU, batched as ours: what a
  rasteriser costs on these cores (MuJoCo's passes are the other rasteriser, OpenGL on Mesa's llvmpipe).

``run()`` returns a flat dict for ``benchmarks.run`` (``render_ms_per_view_240``,
``render_ratio_vs_mujoco``, ``mask_iou_head``, ``mask_iou_wrist_min``, ...).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import mujoco
import numpy as np
import torch

from imac_data.core.render import RasterRenderer, RaycastRenderer
from imac_data.core.robot import aloha
from imac_data.core.robot.model import RobotModel
from imac_data.sources.sim import rig as sim_rig

VIEWS = tuple(sim_rig.CAMERA_NAMES.values())  # cam_high, cam_left_wrist, cam_right_wrist
HEAD = "cam_high"
WRISTS = ("cam_left_wrist", "cam_right_wrist")


# ----------------------------------------------------------------------------- MuJoCo


def _robot_geoms(model: mujoco.MjModel) -> np.ndarray:
    def is_robot(body: str) -> bool:
        return any(body == a or body.startswith(a + "/") for a in aloha.ARMS)

    return np.array([g for g in range(model.ngeom) if is_robot(model.body(model.geom_bodyid[g]).name)])


class MujocoViews:
    """gym-aloha's frozen-camera model at dataset vectors: RGB / depth / segmentation passes."""

    def __init__(self, task: str, height: int, width: int, *, robot_only: bool, fast: bool = True):
        model = sim_rig.load_mujoco_model(task)
        if fast:
            model.vis.quality.shadowsize = 0
            model.vis.quality.offsamples = 0
        model.vis.global_.offwidth = max(int(model.vis.global_.offwidth), width)
        model.vis.global_.offheight = max(int(model.vis.global_.offheight), height)
        robot = _robot_geoms(model)
        if robot_only:
            model.geom_group[np.setdiff1d(np.arange(model.ngeom), robot)] = 5  # hidden group
        self.model, self.data = model, mujoco.MjData(model)
        self.renderer = mujoco.Renderer(model, height=height, width=width)
        self.option = mujoco.MjvOption()
        self.option.sitegroup[:] = 0
        self.near = float(model.vis.map.znear * model.stat.extent)
        self.far = float(model.vis.map.zfar * model.stat.extent)
        self.lut = np.zeros(model.ngeom + 1, dtype=bool)
        self.lut[robot + 1] = True

    def set(self, q14: np.ndarray) -> None:
        m, d = self.model, self.data
        if m.nkey:
            mujoco.mj_resetDataKeyframe(m, d, 0)
        sim_rig.set_mujoco_qpos(m, d, q14)
        mujoco.mj_forward(m, d)

    def pass_(self, camera: str, kind: str) -> np.ndarray:
        r = self.renderer
        r.update_scene(self.data, camera=camera, scene_option=self.option)
        if kind == "rgb":
            return r.render()
        if kind == "depth":
            r.enable_depth_rendering()
            try:
                return r.render()
            finally:
                r.disable_depth_rendering()
        r.enable_segmentation_rendering()
        try:
            return r.render()
        finally:
            r.disable_segmentation_rendering()

    def robot_mask_depth(self, q14: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        self.set(q14)
        out = {}
        for mj_cam, name in sim_rig.CAMERA_NAMES.items():
            seg = self.pass_(mj_cam, "seg")
            geom = np.where(seg[..., 1] == int(mujoco.mjtObj.mjOBJ_GEOM), seg[..., 0], -1)
            depth = self.pass_(mj_cam, "depth").copy()
            out[name] = (self.lut[geom + 1], np.where(depth < 0.999 * self.far, depth, 0.0))
        return out

    def close(self) -> None:
        self.renderer.close()


# ----------------------------------------------------------------------------- episodes


def _workspace_configs(n: int, seed: int) -> np.ndarray:
    from gym_aloha.constants import START_ARM_POSE

    rng = np.random.default_rng(seed)
    start = np.asarray(START_ARM_POSE, dtype=float)
    base = np.r_[start[0:6], 0.5, start[8:14], 0.5]
    spread = np.array([0.5, 0.35, 0.35, 0.6, 0.5, 0.8, 0.5] * 2)
    keys = base + rng.uniform(-1, 1, (5, 14)) * spread
    s = np.linspace(0, len(keys) - 1, n)
    q = np.stack([np.interp(s, np.arange(len(keys)), keys[:, j]) for j in range(14)], axis=1)
    q[:, [6, 13]] = np.clip(q[:, [6, 13]], 0, 1)
    return q


def _episode(task: str, seed: int, height: int, width: int) -> tuple[np.ndarray, dict | None, str]:
    """(qpos (T, 14), visible-robot masks {cam: (T, H, W)} or None, description)."""
    try:
        from imac_data.sources.sim.env import FrameRenderer, robot_mask, segmentation_labels
        from imac_data.sources.sim.recorder import simulate_episode
    except ImportError:
        return _workspace_configs(120, seed), None, "random workspace configurations (no imac_data.sources.sim.recorder)"
    model = sim_rig.load_mujoco_model(task)
    fr = FrameRenderer(model, width, height, depth=False, segmentation=True)
    try:
        ep = simulate_episode(task, seed, renderer=fr)
    finally:
        fr.close()
    labels = segmentation_labels(model)
    visible = {cam: robot_mask(ep.segmentation[cam], labels) for cam in VIEWS}
    return ep.qpos, visible, f"scripted episode seed {seed} ({ep.num_frames} frames, success={ep.success})"


# ----------------------------------------------------------------------------- accuracy


def accuracy(robot: RobotModel, tasks, episodes: int, seed: int, height: int = 240, width: int = 320,
             batch: int = 16) -> dict:
    stats = {}
    for task in tasks:
        oracle = MujocoViews(task, height, width, robot_only=True)
        calib = sim_rig.camera_calibration(oracle.model, width, height)
        ours = RaycastRenderer(robot, near=oracle.near)
        free = RaycastRenderer(robot)
        acc = {c: {"iou": [], "err": [], "visible_iou": [], "near_frac": [], "pixels": []} for c in VIEWS}
        sources = []
        try:
            for e in range(episodes):
                q, visible, what = _episode(task, seed + e, height, width)
                sources.append(what)
                for s in range(0, len(q), batch):
                    qb = torch.as_tensor(q[s:s + batch])
                    views = ours.render(qb, calib)
                    unclipped = free.render(qb, calib)
                    for j in range(len(qb)):
                        ref = oracle.robot_mask_depth(q[s + j])
                        for c in VIEWS:
                            mask = views[c].mask[j].numpy()
                            truth, depth = ref[c]
                            union = (mask | truth).sum()
                            if union:
                                acc[c]["iou"].append((mask & truth).sum() / union)
                            both = mask & truth
                            acc[c]["err"].append(np.abs(views[c].depth[j].numpy()[both] - depth[both]))
                            acc[c]["pixels"].append(int(truth.sum()))
                            if visible is not None:
                                vis = visible[c][s + j]
                                u = (mask | vis).sum()
                                if u:
                                    acc[c]["visible_iou"].append((mask & vis).sum() / u)
                            um = unclipped[c].mask[j]
                            if um.any():
                                acc[c]["near_frac"].append(float((unclipped[c].depth[j][um] < oracle.near)
                                                                 .float().mean()))
        finally:
            oracle.close()
        stats[task] = {"source": sources, "cameras": {}}
        for c in VIEWS:
            a = acc[c]
            err = np.concatenate(a["err"]) if a["err"] else np.zeros(0)
            stats[task]["cameras"][c] = {
                "frames": len(a["pixels"]),
                "mean_robot_px": float(np.mean(a["pixels"])),
                "mean_iou": float(np.mean(a["iou"])),
                "min_iou": float(np.min(a["iou"])),
                "depth_median_abs_mm": float(np.median(err) * 1e3),
                "depth_p99_abs_mm": float(np.percentile(err, 99) * 1e3),
                "visible_mean_iou": float(np.mean(a["visible_iou"])) if a["visible_iou"] else None,
                "nearer_than_near_plane": float(np.mean(a["near_frac"])) if a["near_frac"] else 0.0,
            }
    return stats


# ----------------------------------------------------------------------------- timing


class _RebuildBaseline:
    """Open3D with the posed robot rebuilt every frame: FK, one batched vertex transform
    (vertices pre-concatenated with a link index), BVH build, all views cast."""

    def __init__(self, robot: RobotModel):
        import open3d as o3d

        self.o3d, self.robot = o3d, robot
        links = sorted({m.link for m in robot.visual_meshes})
        self.links = links
        idx = {n: i for i, n in enumerate(links)}
        self.verts = np.concatenate([m.vertices for m in robot.visual_meshes]).astype(np.float32)
        self.vlink = np.concatenate([np.full(len(m.vertices), idx[m.link]) for m in robot.visual_meshes])
        offs = np.cumsum([0] + [len(m.vertices) for m in robot.visual_meshes])[:-1]
        self.faces = o3d.core.Tensor(np.concatenate([m.faces + o for m, o in zip(robot.visual_meshes, offs)])
                                     .astype(np.uint32))
        self._dirs = {}

    def _cam_dirs(self, cam):
        key = (cam.K.tobytes(), cam.width, cam.height)
        if key not in self._dirs:
            v, u = np.mgrid[:cam.height, :cam.width]
            pix = np.stack([u, v, np.ones_like(u)], -1).reshape(-1, 3).astype(np.float64)
            self._dirs[key] = pix @ np.linalg.inv(cam.K).T
        return self._dirs[key]

    def render(self, q: torch.Tensor, calib: dict) -> None:
        poses = self.robot.link_poses(q)
        T = np.take(np.stack([poses[n].float().numpy() for n in self.links]), self.vlink, axis=0)  # (V, 4, 4)
        world = np.einsum("vij,vj->vi", T[:, :3, :3], self.verts) + T[:, :3, 3]
        scene = self.o3d.t.geometry.RaycastingScene()
        scene.add_triangles(self.o3d.core.Tensor(np.ascontiguousarray(world, dtype=np.float32)), self.faces)
        rays = []
        for cam in calib.values():
            Twc = cam.T_world_cam if not cam.is_mounted else poses[cam.link].double().numpy() @ cam.T_link_cam
            d = self._cam_dirs(cam) @ Twc[:3, :3].T
            rays.append(np.concatenate([np.broadcast_to(Twc[:3, 3], d.shape), d], 1))
        scene.cast_rays(self.o3d.core.Tensor(np.concatenate(rays).astype(np.float32)))


def timing(robot: RobotModel, task: str, q: np.ndarray, height: int, width: int, batch: int,
           shipped_frames: int = 4) -> dict:
    """Milliseconds per view (interleaved blocks; medians over blocks)."""
    mj = MujocoViews(task, height, width, robot_only=False)
    calib = sim_rig.camera_calibration(mj.model, width, height)
    ours = RaycastRenderer(robot)
    raster = RasterRenderer(robot)
    rebuild = _RebuildBaseline(robot)
    mj_cams = list(sim_rig.CAMERA_NAMES)
    ours.render(torch.as_tensor(q[:1]), calib)  # warm-up (allocations, caches)
    raster.render(torch.as_tensor(q[:1]), calib)
    rebuild.render(torch.as_tensor(q[0]), calib)
    for c in mj_cams:
        mj.set(q[0])
        for kind in ("rgb", "depth", "seg"):
            mj.pass_(c, kind)
    per = {k: [] for k in ("ours_batch", "ours_single", "raster_batch", "rebuild", "mj_rgb", "mj_depth", "mj_seg")}
    V = len(mj_cams)
    try:
        for s in range(0, len(q) - batch + 1, batch):
            block = q[s:s + batch]
            t = time.perf_counter()
            ours.render(torch.as_tensor(block), calib)
            per["ours_batch"].append((time.perf_counter() - t) / (batch * V))
            t = time.perf_counter()
            for row in block:
                ours.render(torch.as_tensor(row), calib)
            per["ours_single"].append((time.perf_counter() - t) / (batch * V))
            t = time.perf_counter()
            raster.render(torch.as_tensor(block), calib)
            per["raster_batch"].append((time.perf_counter() - t) / (batch * V))
            t = time.perf_counter()
            for row in block:
                rebuild.render(torch.as_tensor(row), calib)
            per["rebuild"].append((time.perf_counter() - t) / (batch * V))
            for kind in ("rgb", "depth", "seg"):
                elapsed = 0.0
                for row in block:
                    mj.set(row)  # kinematics outside the timed region
                    t = time.perf_counter()
                    for c in mj_cams:
                        mj.pass_(c, kind)
                    elapsed += time.perf_counter() - t
                per[f"mj_{kind}"].append(elapsed / (batch * V))
    finally:
        mj.close()
    out = {k: float(np.median(v) * 1e3) for k, v in per.items()}
    # gym-aloha's shipped render settings (shadow map, MSAA), a few frames only
    shipped = MujocoViews(task, height, width, robot_only=False, fast=False)
    try:
        shipped.set(q[0])
        for c in mj_cams:
            shipped.pass_(c, "rgb")
        t_total = 0.0
        for row in q[:shipped_frames]:
            shipped.set(row)
            t = time.perf_counter()
            for c in mj_cams:
                shipped.pass_(c, "rgb")
            t_total += time.perf_counter() - t
        out["mj_rgb_shipped"] = t_total / (shipped_frames * V) * 1e3
    finally:
        shipped.close()
    out["blocks"] = len(per["ours_batch"])
    out["batch"] = batch
    return out


# ----------------------------------------------------------------------------- report


def run(quick: bool = False, episodes: int = 1, seed: int = 0, tasks=aloha.TASKS, timing_frames: int | None = None,
        batch: int = 8, verbose: bool = True) -> dict:
    robot = RobotModel(aloha.robot_config())
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    if quick:
        tasks, episodes = tasks[:1], 1
    acc = accuracy(robot, tasks, episodes, seed)
    timing_frames = timing_frames or (16 if quick else 48)
    q = _workspace_configs(timing_frames, seed + 100)
    times = {f"{h}x{w}": timing(robot, tasks[0], q, h, w, batch) for h, w in ((240, 320), (480, 640))}
    load1 = os.getloadavg()[0]

    cams = {(task, c): acc[task]["cameras"][c] for task in acc for c in VIEWS}
    t240, t480 = times["240x320"], times["480x640"]
    result = {
        "render_ms_per_view_240": t240["ours_batch"],
        "render_ms_per_view_240_single": t240["ours_single"],
        "render_ms_per_view_480": t480["ours_batch"],
        "render_ms_per_view_480_single": t480["ours_single"],
        "render_ratio_vs_mujoco": t240["ours_batch"] / t240["mj_rgb"],
        "render_ratio_vs_mujoco_480": t480["ours_batch"] / t480["mj_rgb"],
        "render_ratio_vs_mujoco_all_passes": t240["ours_batch"] / (t240["mj_rgb"] + t240["mj_depth"] + t240["mj_seg"]),
        "render_ratio_vs_rebuild": t240["ours_batch"] / t240["rebuild"],
        "render_ratio_vs_raster": t240["ours_batch"] / t240["raster_batch"],
        "raster_ms_per_view_240": t240["raster_batch"],
        "mujoco_rgb_ms_per_view_240": t240["mj_rgb"],
        "mujoco_depth_ms_per_view_240": t240["mj_depth"],
        "mask_iou_head": min(cams[(t, HEAD)]["mean_iou"] for t in acc),
        "mask_iou_wrist_min": min(cams[(t, c)]["mean_iou"] for t in acc for c in WRISTS),
        "depth_median_abs_err_mm": max(e["depth_median_abs_mm"] for e in cams.values()),
        "accuracy": acc,
        "timing_ms_per_view": times,
        "load_average": [load0, load1],
        "seconds": time.perf_counter() - t0,
    }
    if verbose:
        print(report(result))
    return result


def report(r: dict) -> str:
    lines = ["Accuracy at 240x320 vs MuJoCo (robot-only oracle; near plane = MuJoCo's)",
             f"{'task':<14} {'camera':<16} {'frames':>6} {'robot px':>8} {'mean IoU':>9} {'min IoU':>8} "
             f"{'|dz| med':>9} {'|dz| p99':>9} {'visible IoU':>11} {'< near':>7}"]
    for task, a in r["accuracy"].items():
        for c, e in a["cameras"].items():
            vis = "-" if e["visible_mean_iou"] is None else f"{e['visible_mean_iou']:.4f}"
            lines.append(f"{task:<14} {c:<16} {e['frames']:>6} {e['mean_robot_px']:>8.0f} {e['mean_iou']:>9.4f} "
                         f"{e['min_iou']:>8.4f} {e['depth_median_abs_mm']:>6.3f} mm {e['depth_p99_abs_mm']:>6.3f} mm "
                         f"{vis:>11} {100 * e['nearer_than_near_plane']:>6.2f}%")
        lines.append(f"  ({task}: {'; '.join(a['source'])})")
    lines += ["", "Time per view (ms; medians over interleaved blocks, 3 views per frame)",
              f"{'size':<8} {'ours B':>7} {'ours 1':>7} {'raster B':>8} {'O3D rebuild':>11} {'MJ RGB':>7} {'MJ depth':>8} "
              f"{'MJ seg':>7} {'MJ RGB shipped':>14} {'ours/MJ RGB':>11} {'ours/MJ all':>11}"]
    for size, t in r["timing_ms_per_view"].items():
        all_ = t["mj_rgb"] + t["mj_depth"] + t["mj_seg"]
        lines.append(f"{size:<8} {t['ours_batch']:>7.2f} {t['ours_single']:>7.2f} {t.get('raster_batch', float('nan')):>8.2f} "
                     f"{t['rebuild']:>11.2f} "
                     f"{t['mj_rgb']:>7.2f} {t['mj_depth']:>8.2f} {t['mj_seg']:>7.2f} {t['mj_rgb_shipped']:>14.2f} "
                     f"{t['ours_batch'] / t['mj_rgb']:>11.2f} {t['ours_batch'] / all_:>11.2f}")
    lines.append(f"(ours B: batch of {next(iter(r['timing_ms_per_view'].values()))['batch']} frames; ours 1: one "
                 f"frame per call; raster B: the torch rasteriser, batched. ours = RGB + mask + depth + link ids in one "
                 f"pass; MJ all = RGB + depth + seg "
                 f"passes. load average {r['load_average'][0]:.1f} -> {r['load_average'][1]:.1f} on "
                 f"{os.cpu_count()} cores; {r['seconds']:.0f} s)")
    keys = [k for k, v in r.items() if isinstance(v, float)]
    lines += ["", "  ".join(f"{k}={r[k]:.4g}" for k in keys)]
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.render_vs_mujoco", description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="one task, one episode, fewer timing frames")
    p.add_argument("--episodes", type=int, default=1, help="episodes per task")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--timing-frames", type=int, default=None)
    p.add_argument("--batch", type=int, default=8)
    p.add_argument("--json", type=Path, default=None, help="also write the result dict here")
    args = p.parse_args(argv)
    r = run(quick=args.quick, episodes=args.episodes, seed=args.seed, timing_frames=args.timing_frames,
            batch=args.batch)
    if args.json:
        args.json.write_text(json.dumps(r, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
