"""``qa refine``: fix a calibration from the recordings themselves.

    python -m imac_data.qa refine SOURCE --recipe R.yaml --calibration calib.json --out refined.json
        [--robot-pixels auto|sim|edges|MASK_DIR] [--cameras cam_high,...] [--frames 8]
        [--method gradient|nelder-mead|powell] [--refine-focal] [--near METRES]
        [--report DIR] [--overwrite]

Reads the frames, picks the robot's pixels, runs :mod:`imac_data.calibrate` per camera and
writes:

* ``refined.json``: the whole rig in the README's calibration format, the refined cameras
  replaced (never the input file: an output that is, contains or lies inside an input is
  refused before any work);
* the report directory (default ``refined.report/`` beside it): ``report.json`` (per
  camera: the frames used, before/after IoU, boundary residual in pixels, pose change per
  axis, time) and ``{camera}_before.png`` / ``{camera}_after.png``, the frames with the
  rendered robot's outline in green over the robot pixels' outline in magenta.

Both appear only complete (written under temporary names, renamed at the end).

Robot pixels (``--robot-pixels``):

* ``sim``: the simulator's ground truth, recorded in the episodes (geom segmentation);
* a directory of masks from any segmenter: ``DIR/<episode file stem>/<camera>/<frame:06d>.png``,
  nonzero = robot; only frames with a mask are used;
* ``edges``: the built-in cue, no learned model: image edges near the current overlay
  (:func:`imac_data.calibrate.image_edges`); the rendered outline is pulled onto them, in
  three rounds with a search margin shrinking from 8% of the image;
* ``auto`` (default): ``sim`` when the episodes carry a segmentation, else ``edges``.

SOURCE is a directory of raw ALOHA/AgileX HDF5 episodes or one episode file; the frame
reading sits behind :class:`HDF5Frames`, the one thing a LeRobot source has to replace.
``--near`` is the renderer's near clip plane: by default the simulated rig's (MuJoCo clips
at ``znear * extent``, 0.166 m) when the episodes are marked simulated, else 0 (real
cameras do not clip).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import h5py
import numpy as np
import torch

from imac_data.calibrate import (CameraFit, RefineConfig, image_edges, pose_change, refine_camera, select_frames,
                                 silhouette_agreement)
from imac_data.cameras import Camera, load_calibration, save_calibration
from imac_data.errors import InputError

__all__ = ["HDF5Frames", "refine_calibration", "add_arguments", "run", "main"]

OUTLINE_RGB = (0, 255, 0)  # rendered robot
TARGET_RGB = (255, 0, 255)  # robot pixels

# ----------------------------------------------------------------------------- frames


class HDF5Frames:
    """Frames of raw ALOHA HDF5 episodes (a directory, or one file), read only where asked.

    The interface the refinement needs (a LeRobot dataset can provide the same):
    ``episodes``, ``cameras``, ``simulated``, ``joints(ep)``, ``images(ep, cam, frames)``,
    ``robot_masks(ep, cam, frames, links)`` (ground truth or ``None``).
    """

    def __init__(self, source: str | Path):
        from imac_data.aloha_hdf5 import episode_paths, probe_episode

        source = Path(source)
        if source.is_file():
            paths = [source]
        elif source.is_dir():
            paths = episode_paths(source)
        else:
            raise InputError(f"source not found: {source} (a directory of HDF5 episodes or one episode file)")
        probes = [probe_episode(p) for p in paths]
        self.source = source
        self.episodes = [str(p) for p in paths]
        self.cameras = sorted(set.intersection(*(set(p["cameras"]) for p in probes)))
        with h5py.File(paths[0], "r") as f:
            self.simulated = bool(f.attrs.get("sim", False))
            self.has_segmentation = "observations/segmentation" in f

    def joints(self, episode: str) -> np.ndarray:
        with h5py.File(episode, "r") as f:
            return np.asarray(f["observations/qpos"][()], dtype=np.float64)

    def images(self, episode: str, camera: str, frames: Sequence[int]) -> np.ndarray:
        from imac_data.aloha_hdf5 import _camera_names, _decode_jpeg_stack

        idx = np.asarray(frames, dtype=np.int64)
        key = f"observations/images/{camera}"
        with h5py.File(episode, "r") as f:
            if bool(f.attrs.get("compress", False)):
                row = _camera_names(f, Path(episode)).index(camera)
                lengths = f["compress_len"][row][idx]
                return _decode_jpeg_stack(f[key][idx], lengths, Path(episode), key)
            return f[key][idx]

    def robot_masks(self, episode: str, camera: str, frames: Sequence[int], links: Sequence[str]) -> np.ndarray | None:
        from imac_data.qa import ground_truth_robot_mask

        key = f"observations/segmentation/{camera}"
        with h5py.File(episode, "r") as f:
            if key not in f:
                return None
            labels = {int(k): tuple(v) for k, v in json.loads(f.attrs.get("segmentation_labels", "{}")).items()}
            seg = f[key][np.asarray(frames, dtype=np.int64)]
        return ground_truth_robot_mask(seg, labels, links)


def _mask_dir_frames(mask_dir: Path, episode: str, camera: str) -> dict[int, Path]:
    folder = mask_dir / Path(episode).stem / camera
    out = {}
    if folder.is_dir():
        for p in folder.glob("*.png"):
            if p.stem.isdigit():
                out[int(p.stem)] = p
    return out


def _read_mask(path: Path, hw: tuple[int, int]) -> np.ndarray:
    m = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if m is None:
        raise InputError(f"{path}: not a readable PNG mask")
    if m.shape != hw:
        raise InputError(f"{path}: mask is {m.shape[1]}x{m.shape[0]}, the camera's frames are {hw[1]}x{hw[0]}")
    return m > 0


# ----------------------------------------------------------------------------- the command


@dataclass
class _CameraProblem:
    camera: str
    refs: list[tuple[str, int]]  # (episode, frame) of the chosen frames
    q: np.ndarray  # (N, D)
    images: np.ndarray  # (N, H, W, 3)
    target: np.ndarray | None  # (N, H, W) robot probability or image edges (None until the edge cue makes them)


def _default_near(frames: HDF5Frames) -> float:
    if not frames.simulated:
        return 0.0
    from imac_data.aloha import load_mujoco_model

    model = load_mujoco_model("transfer_cube")  # every task's model has the same visual settings
    return float(model.vis.map.znear * model.stat.extent)


def _candidates(T: int, budget: int) -> np.ndarray:
    return np.arange(0, T, max(1, math.ceil(T / budget)))


def _gather(frames: HDF5Frames, cam_name: str, camera: Camera, renderer, pixels: str, mask_dir: Path | None,
            count: int, min_separation: float, budget: int) -> _CameraProblem:
    """Choose the frames of one camera and read their images and robot pixels."""
    links = renderer.link_names
    per_episode = max(8, budget // len(frames.episodes))
    q_all, cov_all, refs = [], [], []
    for ep in frames.episodes:
        q = frames.joints(ep)
        if pixels == "masks":
            avail = _mask_dir_frames(mask_dir, ep, cam_name)
            idx = np.array(sorted(t for t in avail if 0 <= t < len(q)), dtype=np.int64)
            idx = idx[_candidates(len(idx), per_episode)] if len(idx) else idx
            hw = frames.images(ep, cam_name, [0]).shape[1:3]
            cov = [float(_read_mask(avail[t], hw).mean()) for t in idx]
        else:
            idx = _candidates(len(q), per_episode)
            if pixels == "sim":
                cov = []
                for i in range(0, len(idx), 16):  # bounded memory, whatever the episode length
                    m = frames.robot_masks(ep, cam_name, idx[i:i + 16], links)
                    if m is None:
                        raise InputError(f"{ep}: no ground-truth segmentation for camera {cam_name!r}; "
                                         "choose --robot-pixels edges or a mask directory")
                    cov += m.mean(axis=(1, 2)).tolist()
            else:  # edges: where the current calibration renders the robot
                cov = renderer.render(torch.as_tensor(q[idx]), {cam_name: camera},
                                      resolution=(60, 80))[cam_name].mask.float().mean(dim=(1, 2)).numpy()
        q_all.append(q[idx])
        cov_all.append(np.asarray(cov, dtype=np.float64))
        refs += [(ep, int(t)) for t in idx]
    if not refs:
        raise InputError(f"no robot visible in camera {cam_name!r}: no frame has a mask under {mask_dir}")
    sel = select_frames(np.concatenate(q_all), np.concatenate(cov_all), count, min_separation=min_separation,
                        camera=cam_name)
    chosen = [refs[i] for i in sel]
    q = np.concatenate(q_all)[sel]
    images, target = [], []
    for ep in dict.fromkeys(e for e, _ in chosen):  # refs are in episode order, frames ascending
        ts = [t for e, t in chosen if e == ep]
        images.append(frames.images(ep, cam_name, ts))
        if pixels == "sim":
            target.append(frames.robot_masks(ep, cam_name, ts, links))
        elif pixels == "masks":
            avail = _mask_dir_frames(mask_dir, ep, cam_name)
            target.append(np.stack([_read_mask(avail[t], images[-1].shape[1:3]) for t in ts]))
    return _CameraProblem(cam_name, chosen, q, np.concatenate(images),
                          np.concatenate(target).astype(np.float32) if target else None)


def _draw(images: np.ndarray, rendered: np.ndarray, target: np.ndarray, title: str, edges: bool) -> np.ndarray:
    """A grid of the frames (at most 8, two rows), outlines of the robot pixels (or the image
    edges the cue found) and of the render."""
    from imac_data.qa import outline

    tiles = []
    for img, r, g in zip(images[:8], rendered[:8], target[:8]):
        t = max(1, round(img.shape[0] / 240))
        out = img.copy()
        out[g if edges else outline(g >= 0.5, t)] = TARGET_RGB
        out[outline(r, t)] = OUTLINE_RGB
        tiles.append(out)
    while len(tiles) % 4 and len(tiles) > 4:
        tiles.append(np.zeros_like(tiles[0]))
    rows = [np.concatenate(tiles[i:i + 4], 1) for i in range(0, len(tiles), 4)]
    grid = np.concatenate(rows, 0)
    scale = min(1.0, 1600 / grid.shape[1])
    if scale < 1:
        grid = cv2.resize(grid, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    cv2.putText(grid, title, (8, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (0, 0, 0), 4, cv2.LINE_AA)
    cv2.putText(grid, title, (8, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (255, 255, 255), 1, cv2.LINE_AA)
    return grid


def _edge_target(images, renderer, camera: Camera, q, margin_px: int) -> np.ndarray:
    rendered = renderer.render(torch.as_tensor(q), {camera.name: camera},
                               resolution=images.shape[1:3])[camera.name].mask.numpy()
    return image_edges(images, rendered, margin_px=margin_px)


def refine_calibration(source: str | Path, calibration: str | Path, out: str | Path, *, robot="aloha",
                       recipe: str | Path | None = None, robot_pixels: str = "auto",
                       cameras: Sequence[str] | None = None, frames: int = 8, min_separation: float = 0.1,
                       config: RefineConfig | None = None, near: float | None = None,
                       report: str | Path | None = None, overwrite: bool = False, edge_rounds: int = 3,
                       edge_margin: float = 0.08,
                       candidate_budget: int = 400, log=None) -> dict:
    """Refine the calibration ``calibration`` from the episodes in ``source``; write ``out`` and the
    report directory; return the report dict. All inputs are checked before any work."""
    from imac_data.render import make_renderer
    from imac_data.robot import RobotModel
    from imac_data.safety import refuse_overlap

    log = log or (lambda msg: None)
    config = config or RefineConfig()
    source, calibration, out = Path(source), Path(calibration), Path(out)
    report = Path(report) if report is not None else out.with_name(out.stem + ".report")
    if frames < 3:
        raise InputError(f"--frames must be at least 3 (got {frames}): one or two views hardly constrain a pose")
    inputs = {"source episodes": source, "calibration": calibration,
              "recipe": Path(recipe) if recipe is not None else None}
    for path, what in ((out, "--out"), (report, "--report")):
        for name, p in inputs.items():
            if p is not None and p.exists() and path.resolve() == p.resolve():
                raise InputError(f"{what} {path} is the {name}: the input is never overwritten; choose another name")
        refuse_overlap(path, inputs, what=what)
        if path.exists() and not overwrite:
            raise InputError(f"{what} {path} exists; pass --overwrite to replace it")
    if out.exists() and out.is_dir():
        raise InputError(f"--out {out} is a directory; give a file name such as refined.json")
    calib = load_calibration(calibration)
    if recipe is not None:
        from imac_data.build import robot_of
        from imac_data.recipes import load_recipe

        robot = robot_of(load_recipe(recipe))
    elif isinstance(robot, str):
        from imac_data.qa import ROBOTS

        if robot not in ROBOTS:
            raise InputError(f"unknown robot {robot!r}; known: {sorted(ROBOTS)}")
        robot = ROBOTS[robot]()
    elif not isinstance(robot, RobotModel):
        raise InputError(f"robot must be a name or a RobotModel, got {type(robot).__name__}")
    src = HDF5Frames(source)
    cams = list(cameras) if cameras else [c for c in src.cameras if c in calib]
    missing = [c for c in cams if c not in src.cameras]
    if missing:
        raise InputError(f"{source}: camera(s) {missing} not in the episodes (they have {src.cameras})")
    uncalibrated = [c for c in cams if c not in calib]
    if uncalibrated:
        raise InputError(f"{calibration}: no calibration for camera(s) {uncalibrated} (calibrated: {sorted(calib)})")
    if not cams:
        raise InputError(f"no camera is both in the episodes ({src.cameras}) and calibrated ({sorted(calib)})")
    q0 = src.joints(src.episodes[0])
    if q0.shape[1] != robot.dof:
        raise InputError(f"{src.episodes[0]}: joint vectors have {q0.shape[1]} entries, robot {robot.name!r} "
                         f"expects {robot.dof}")
    mask_dir = None
    if robot_pixels == "auto":
        robot_pixels = "sim" if src.has_segmentation else "edges"
    if robot_pixels not in ("sim", "edges"):
        mask_dir = Path(robot_pixels)
        if not mask_dir.is_dir():
            raise InputError(f"--robot-pixels {robot_pixels}: not 'auto', 'sim', 'edges' or a mask directory")
        pixels = "masks"
    else:
        pixels = robot_pixels
    near = _default_near(src) if near is None else float(near)
    renderer = make_renderer(robot, near=near)
    rig = renderer.prepare_cameras({c: calib[c] for c in cams})  # mounted links must exist

    t0, c0 = time.perf_counter(), time.process_time()
    result = {"source": str(source), "calibration": str(calibration), "out": str(out), "robot": robot.name,
              "robot_urdf_sha256": robot.urdf_hash, "robot_pixels": str(robot_pixels), "near_m": near,
              "config": config.to_dict(), "cameras": {}}
    refined = dict(calib)
    overlays = {}
    for c in cams:
        log(f"[refine] {c}: choosing frames")
        size = src.images(src.episodes[0], c, [0]).shape[1:3]
        cam0 = rig[c] if (rig[c].height, rig[c].width) == tuple(size) else rig[c].rescaled(size[1], size[0])
        prob = _gather(src, c, cam0, renderer, pixels, mask_dir, frames, min_separation, candidate_budget)
        log(f"[refine] {c}: frames {[f'{Path(e).stem}:{t}' for e, t in prob.refs]}")
        if pixels == "edges":
            margin = max(2, round(edge_margin * max(size)))
            cam, fits = cam0, []
            for k in range(edge_rounds):  # the search margin shrinks as the overlay improves
                prob.target = _edge_target(prob.images, renderer, cam, prob.q, margin)
                fits.append(refine_camera(renderer, cam, prob.q, prob.target, config, edges=True, log=log))
                cam = fits[-1].camera
                margin = max(2, margin // 2)
            fit = CameraFit(camera=cam, initial=cam0, update=sum(f.update for f in fits),
                            renders=sum(f.renders for f in fits), wall_s=sum(f.wall_s for f in fits),
                            cpu_s=sum(f.cpu_s for f in fits), history=[h for f in fits for h in f.history])
        else:
            fit = refine_camera(renderer, cam0, prob.q, prob.target, config, log=log)
        q = torch.as_tensor(prob.q)
        before = renderer.render(q, {c: cam0})[c].mask.numpy()
        after = renderer.render(q, {c: fit.camera})[c].mask.numpy()
        edges = pixels == "edges"
        agree0 = silhouette_agreement(before, prob.target, edges=edges)
        agree1 = silhouette_agreement(after, prob.target, edges=edges)
        out_cam = fit.camera if (fit.camera.height, fit.camera.width) == (calib[c].height, calib[c].width) \
            else fit.camera.rescaled(calib[c].width, calib[c].height)
        score = "boundary_px" if edges else "iou"
        kept = not (agree1[score] <= agree0[score] if edges else agree1[score] >= agree0[score])
        if kept:  # never hand back a worse calibration
            log(f"[refine] {c}: refinement did not improve the overlay ({score} {agree0[score]:.4f} -> "
                f"{agree1[score]:.4f}); keeping the input calibration for this camera")
            out_cam, after, agree1 = calib[c], before, agree0
        refined[c] = out_cam
        result["cameras"][c] = {
            "mounted_on": calib[c].link, "frames": [[e, t] for e, t in prob.refs], "kept_input": kept,
            "iou_before": agree0["iou"], "iou_after": agree1["iou"],
            "iou_per_frame_before": agree0["iou_per_frame"], "iou_per_frame_after": agree1["iou_per_frame"],
            "boundary_px_before": agree0["boundary_px"], "boundary_px_after": agree1["boundary_px"],
            "pose_change": pose_change(calib[c], out_cam),
            "focal_change_pct": 100.0 * (out_cam.K[0, 0] / calib[c].K[0, 0] - 1.0),
            "renders": fit.renders, "wall_s": fit.wall_s, "cpu_s": fit.cpu_s,
        }
        overlays[c] = tuple(_draw(prob.images, m, prob.target, f"{c} {when}: " + (
            f"outline {a['boundary_px']:.2f} px from the edges" if edges else f"IoU {a['iou']:.4f}"), edges)
            for when, m, a in (("before", before, agree0), ("after", after, agree1)))
    result["wall_s"] = time.perf_counter() - t0
    result["cpu_s"] = time.process_time() - c0
    result["load_avg"] = list(os.getloadavg())

    # write: temporary names beside the outputs, renamed into place at the end
    out.parent.mkdir(parents=True, exist_ok=True)
    report.parent.mkdir(parents=True, exist_ok=True)
    tmp_json = out.with_name(f".{out.name}.tmp")
    tmp_dir = Path(tempfile.mkdtemp(prefix=f".{report.name}.", dir=report.parent))
    try:
        save_calibration(tmp_json, refined)
        load_calibration(tmp_json)  # what we wrote loads back
        for c, (b, a) in overlays.items():
            cv2.imwrite(str(tmp_dir / f"{c}_before.png"), b[..., ::-1])
            cv2.imwrite(str(tmp_dir / f"{c}_after.png"), a[..., ::-1])
        (tmp_dir / "report.json").write_text(json.dumps(result, indent=2))
        if report.exists():
            import shutil

            shutil.rmtree(report)
        tmp_dir.rename(report)
        tmp_json.replace(out)
    except BaseException:
        import shutil

        tmp_json.unlink(missing_ok=True)
        shutil.rmtree(tmp_dir, ignore_errors=True)
        raise
    result["report"] = str(report)
    return result


# ----------------------------------------------------------------------------- CLI


def format_report(result: dict) -> str:
    lines = [f"wrote {result['out']} and {result['report']}/ (robot pixels: {result['robot_pixels']}, "
             f"{result['wall_s']:.0f} s)",
             f"{'camera':<18} {'IoU before':>10} {'after':>7} {'bdry px':>8} {'after':>6}  "
             f"{'x mm':>7} {'y mm':>7} {'z mm':>7} {'rx deg':>7} {'ry deg':>7} {'rz deg':>7}"]
    def iou(x):
        return "-" if x is None else f"{x:.4f}"

    for c, e in result["cameras"].items():
        p = e["pose_change"]
        lines.append(f"{c:<18} {iou(e['iou_before']):>10} {iou(e['iou_after']):>7} {e['boundary_px_before']:>8.2f} "
                     f"{e['boundary_px_after']:>6.2f}  " + " ".join(f"{p[k]:>7.2f}" for k in
                                                                ("x_mm", "y_mm", "z_mm", "rx_deg", "ry_deg", "rz_deg")))
    lines.append("pose change in each camera's own axes (x right, y down, z forward); bdry px = mean distance "
                 "between the rendered and the observed outlines (edges cue: to the nearest image edge)")
    return "\n".join(lines)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("source", help="directory of raw HDF5 episodes, or one episode file")
    p.add_argument("--calibration", required=True, help="calibration JSON to refine (never modified)")
    p.add_argument("--out", required=True, help="refined calibration JSON to write")
    p.add_argument("--recipe", default=None, help="take the robot (URDF, joint map) from this build recipe")
    p.add_argument("--robot", default="aloha", help="robot by name when no --recipe is given")
    p.add_argument("--robot-pixels", default="auto",
                   help="where the robot's pixels come from: auto (default: sim if recorded, else edges), sim, "
                        "edges, or a mask directory DIR/<episode stem>/<camera>/<frame:06d>.png")
    p.add_argument("--cameras", default=None, help="comma-separated cameras (default: every calibrated one)")
    p.add_argument("--frames", type=int, default=8, help="frames per camera (default 8)")
    p.add_argument("--min-separation", type=float, default=0.1,
                   help="smallest joint-space distance between chosen frames (default 0.1)")
    p.add_argument("--method", default=None, help="gradient (default), nelder-mead or powell")
    p.add_argument("--refine-focal", action="store_true", help="also refine the focal length")
    p.add_argument("--near", type=float, default=None, help="renderer near plane in metres (default: see docs)")
    p.add_argument("--report", default=None, help="report directory (default: <out>.report beside --out)")
    p.add_argument("--overwrite", action="store_true", help="replace existing outputs (never inputs)")


def run(args: argparse.Namespace) -> int:
    try:
        over = {}
        if args.method:
            over["method"] = args.method
        if args.refine_focal:
            over["refine_focal"] = True
        config = RefineConfig(**over)
        cams = [c for c in args.cameras.split(",") if c] if args.cameras else None
        result = refine_calibration(args.source, args.calibration, args.out, robot=args.robot, recipe=args.recipe,
                                    robot_pixels=args.robot_pixels, cameras=cams, frames=args.frames,
                                    min_separation=args.min_separation, config=config, near=args.near,
                                    report=args.report, overwrite=args.overwrite,
                                    log=lambda m: print(m, file=sys.stderr))
    except InputError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(format_report(result))
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m imac_data.refine", description=__doc__.split("\n\n")[0])
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
