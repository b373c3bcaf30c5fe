"""Calibration check: draw the rendered robot over the real frames.

Users cannot trust motion controls whose calibration they have not seen. This
renders the robot (URDF + FK at each frame's configuration) into every camera
with the calibration and draws its outline over the recorded images; where the
episode carries a ground-truth robot mask (simulated episodes: per-pixel geom
segmentation + labels), it also reports the per-frame mask IoU.

    python -m imac_data.qa refine SOURCE [--recipe R.yaml] [--calibration CALIB.json] --out REFINED.json
        (imac_data.refine)
    python -m imac_data.qa overlay EPISODE.hdf5 --calibration CALIB.json --out DIR
        [--robot aloha] [--source state|action] [--format mp4|png]
        [--frames START:STOP:STEP] [--cameras cam_high,cam_left_wrist] [--overwrite]
    python -m imac_data.qa preview ROOT --episode N [--out FILE.mp4]   (imac_data/preview.py)

Writes into ``DIR`` (created atomically: a temporary sibling renamed into place
only when everything succeeded, so a failure leaves nothing behind):

* ``{camera}.mp4`` (H.264) or ``{camera}/{frame:06d}.png``: real frame, rendered
  robot outline in green, ground-truth outline in magenta (when present), frame
  index and IoU in the corner;
* ``iou.csv`` (when a ground-truth mask exists): ``frame,{camera},...``;
* ``summary.json``: inputs, settings, per-camera mean/min IoU and rendered coverage.

The default ``--source state`` renders the measured joint state, which is what
the images show; ``--source action`` renders what the motion-image stream shows
(the controller map of :mod:`imac_data.motion`), lagging the images by the
controller's tracking delay.

Inputs for now: a raw ALOHA HDF5 episode (:mod:`imac_data.aloha_hdf5`), a
calibration JSON (:func:`imac_data.cameras.load_calibration`) and the robot
``aloha`` (the gym-aloha ViperX pair, :func:`imac_data.aloha.robot_config`).
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path

import cv2
import numpy as np
import torch

from imac_data.errors import InputError

__all__ = ["ROBOTS", "overlay", "outline", "mask_iou", "ground_truth_robot_mask", "main"]

OUTLINE_RGB = (0, 255, 0)  # rendered robot
TRUTH_RGB = (255, 0, 255)  # ground-truth robot mask


def _aloha_robot():
    from imac_data.aloha import robot_config
    from imac_data.robot import RobotModel

    return RobotModel(robot_config())


# Robot descriptions the CLI knows by name (their rig: imac_data.rig.Rig.from_platform).
ROBOTS: dict[str, Callable] = {"aloha": _aloha_robot}
_PLATFORMS = {"aloha": "aloha_sim"}


# ----------------------------------------------------------------------------- pieces


def outline(mask: np.ndarray, thickness: int = 1) -> np.ndarray:
    """Boundary pixels of a boolean mask ``(H, W)`` (inside the mask, ``thickness`` px wide)."""
    m = np.ascontiguousarray(mask, dtype=np.uint8)
    k = 2 * thickness + 1
    eroded = cv2.erode(m, np.ones((k, k), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=0)
    return (m > 0) & (eroded == 0)


def mask_iou(pred: np.ndarray, truth: np.ndarray) -> float:
    """Intersection over union of two boolean masks; NaN when both are empty."""
    union = np.logical_or(pred, truth).sum()
    if union == 0:
        return float("nan")
    return float(np.logical_and(pred, truth).sum() / union)


def ground_truth_robot_mask(segmentation: np.ndarray, labels: dict[int, tuple[str, str]],
                            robot_links: Sequence[str]) -> np.ndarray:
    """Robot pixels of a geom-id segmentation (``-1`` = none): geoms whose body is a robot
    link (our MJCF->URDF export keeps MuJoCo body names as link names)."""
    links = set(robot_links)
    ids = [int(g) for g, (_, body) in labels.items() if body in links]
    seg = np.asarray(segmentation).astype(np.int64)
    if not ids:
        return np.zeros(seg.shape, dtype=bool)
    lut = np.zeros(max(max(ids), int(seg.max(initial=-1))) + 2, dtype=bool)
    lut[np.array(ids) + 1] = True
    return lut[np.clip(seg, -1, None) + 1]


def _parse_frames(spec: str | None, T: int) -> range:
    if spec is None:
        return range(T)
    parts = spec.split(":")
    if len(parts) > 3:
        raise InputError(f"--frames must be START:STOP:STEP, got {spec!r}")
    try:
        values = [int(p) if p.strip() else None for p in parts]
    except ValueError:
        raise InputError(f"--frames must be integers START:STOP:STEP, got {spec!r}") from None
    if len(values) == 1:
        if values[0] is None or not -T <= values[0] < T:
            raise InputError(f"--frames {spec!r}: frame out of range for an episode of {T} frames")
        i = values[0] % T
        return range(i, i + 1)
    step = values[2] if len(values) == 3 and values[2] is not None else 1
    if step <= 0:
        raise InputError(f"--frames {spec!r}: step must be positive")
    r = range(T)[slice(values[0], values[1], step)]
    if len(r) == 0:
        raise InputError(f"--frames {spec!r} selects no frame of an episode of {T} frames")
    return r


def _draw(frame: np.ndarray, rendered: np.ndarray, truth: np.ndarray | None, text: str) -> np.ndarray:
    out = frame.copy()
    t = max(1, round(frame.shape[0] / 480))
    if truth is not None:
        out[outline(truth, t)] = TRUTH_RGB
    out[outline(rendered, t)] = OUTLINE_RGB
    scale = 0.35 * max(1.0, frame.shape[0] / 240)
    cv2.putText(out, text, (4, int(12 * scale / 0.35)), cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), 3 * t,
                cv2.LINE_AA)
    cv2.putText(out, text, (4, int(12 * scale / 0.35)), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), t,
                cv2.LINE_AA)
    return out


class _Mp4:
    def __init__(self, path: Path, width: int, height: int, fps: float):
        import av
        from fractions import Fraction

        self.container = av.open(str(path), mode="w")
        self.stream = self.container.add_stream("libx264", rate=Fraction(fps).limit_denominator(1000))
        self.stream.width, self.stream.height = width + width % 2, height + height % 2
        self.stream.pix_fmt = "yuv420p"
        self.stream.options = {"crf": "18", "preset": "veryfast"}
        self._av = av

    def write(self, rgb: np.ndarray) -> None:
        h, w = self.stream.height, self.stream.width
        if rgb.shape[:2] != (h, w):
            rgb = np.pad(rgb, ((0, h - rgb.shape[0]), (0, w - rgb.shape[1]), (0, 0)))
        frame = self._av.VideoFrame.from_ndarray(np.ascontiguousarray(rgb), format="rgb24")
        for packet in self.stream.encode(frame):
            self.container.mux(packet)

    def close(self) -> None:
        for packet in self.stream.encode():
            self.container.mux(packet)
        self.container.close()


# ----------------------------------------------------------------------------- overlay


def overlay(episode_path: str | Path, calibration_path: str | Path, out_dir: str | Path, *,
            robot="aloha", source: str = "state", fmt: str = "mp4", frames: str | None = None,
            cameras: Sequence[str] | None = None, overwrite: bool = False, batch: int = 8,
            renderer=None, controller=None) -> dict:
    """Write the overlay of one episode into ``out_dir`` and return the summary dict.

    ``robot``: a name in :data:`ROBOTS` or a :class:`~imac_data.robot.RobotModel`.
    All inputs are validated before anything is written; the output directory appears
    only complete (temporary sibling renamed into place).
    """
    from imac_data.aloha_hdf5 import read_episode
    from imac_data.cameras import load_calibration
    from imac_data.motion import SOURCES, frame_configurations
    from imac_data.render import make_renderer
    from imac_data.robot import RobotModel
    from imac_data.safety import check_replaceable

    episode_path, out_dir = Path(episode_path), Path(out_dir)
    if fmt not in ("mp4", "png"):
        raise InputError(f"--format must be mp4 or png, got {fmt!r}")
    if source not in SOURCES:
        raise InputError(f"--source must be one of {SOURCES}, got {source!r}")
    if out_dir.exists() and not overwrite:
        raise InputError(f"output {out_dir} exists; pass --overwrite to replace it")
    check_replaceable(out_dir, made_by="summary.json", what="output")
    calib = load_calibration(calibration_path)
    if isinstance(robot, str):
        if robot not in ROBOTS:
            raise InputError(f"unknown robot {robot!r}; known: {sorted(ROBOTS)}")
        robot_name, robot = robot, ROBOTS[robot]()
    elif isinstance(robot, RobotModel):
        robot_name = robot.name
    else:
        raise InputError(f"robot must be a name in {sorted(ROBOTS)} or a RobotModel, got {type(robot).__name__}")
    ep = read_episode(episode_path, cameras=None, load_depth=False, load_segmentation=True)
    cams = list(cameras) if cameras else ep.cameras
    missing_ep = [c for c in cams if c not in ep.images]
    if missing_ep:
        raise InputError(f"{episode_path}: camera(s) {missing_ep} not in the episode (has {ep.cameras})")
    missing_cal = [c for c in cams if c not in calib]
    if missing_cal:
        raise InputError(f"{calibration_path}: no calibration for camera(s) {missing_cal} "
                         f"(calibrated: {sorted(calib)}); pick cameras with --cameras")
    if ep.qpos.shape[1] != robot.dof:
        raise InputError(f"{episode_path}: joint vectors have {ep.qpos.shape[1]} entries, robot "
                         f"{robot.name!r} expects {robot.dof}")
    renderer = renderer or make_renderer(robot)
    rig = {}
    for c in cams:
        h, w = ep.images[c].shape[1:3]
        cam = calib[c]
        rig[c] = cam if (cam.height, cam.width) == (h, w) else cam.rescaled(w, h)
    rig = renderer.prepare_cameras(rig)  # mounted links must exist
    if controller is None and source == "action" and robot_name in _PLATFORMS:
        from imac_data.rig import Rig

        controller = Rig.from_platform(_PLATFORMS[robot_name], rig, robot=robot).controller
    kwargs = {} if controller is None else {"controller": controller}
    q_all = frame_configurations(ep.qpos, ep.action, source=source, **kwargs)
    robot.joint_positions(torch.as_tensor(q_all))  # wrong length / non-finite -> InputError now
    sel = _parse_frames(frames, ep.num_frames)
    truth_links = renderer.link_names
    has_truth = {c: c in ep.segmentation and bool(ep.segmentation_labels) for c in cams}
    fps = (ep.fps or 50.0) / sel.step

    made = [p for p in reversed(out_dir.absolute().parents) if not p.exists()]  # removed again on failure
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.", dir=out_dir.parent))
    writers: dict[str, _Mp4] = {}
    try:
        for c in cams:
            h, w = ep.images[c].shape[1:3]
            if fmt == "mp4":
                writers[c] = _Mp4(tmp / f"{c}.mp4", w, h, fps)
            else:
                (tmp / c).mkdir()
        ious = {c: [] for c in cams}
        coverage = {c: [] for c in cams}
        idx = list(sel)
        for s in range(0, len(idx), batch):
            chunk = idx[s:s + batch]
            views = renderer.render(torch.as_tensor(q_all[chunk]), rig)
            for c in cams:
                masks = views[c].mask.cpu().numpy()
                for j, t in enumerate(chunk):
                    truth = None
                    if has_truth[c]:
                        truth = ground_truth_robot_mask(ep.segmentation[c][t], ep.segmentation_labels, truth_links)
                        ious[c].append(mask_iou(masks[j], truth))
                    coverage[c].append(float(masks[j].mean()))
                    text = f"{c} t={t}" + (f" IoU={ious[c][-1]:.3f}" if truth is not None else "")
                    img = _draw(ep.images[c][t], masks[j], truth, text)
                    if fmt == "mp4":
                        writers[c].write(img)
                    else:
                        cv2.imwrite(str(tmp / c / f"{t:06d}.png"), img[..., ::-1])
        for wr in writers.values():
            wr.close()
        writers = {}

        summary = {
            "episode": str(episode_path), "calibration": str(calibration_path), "robot": robot_name,
            "robot_urdf_sha256": robot.urdf_hash, "source": source, "format": fmt,
            "frames": [sel.start, sel.stop, sel.step], "num_frames": len(idx), "fps": fps,
            "cameras": {},
        }
        for c in cams:
            entry = {"width": rig[c].width, "height": rig[c].height,
                     "mean_rendered_coverage": float(np.mean(coverage[c])) if coverage[c] else None}
            if has_truth[c]:
                vals = np.array(ious[c], dtype=float)
                ok = vals[np.isfinite(vals)]
                entry.update({"mean_iou": float(ok.mean()) if len(ok) else None,
                              "min_iou": float(ok.min()) if len(ok) else None})
            summary["cameras"][c] = entry
        if any(has_truth.values()):
            lines = ["frame," + ",".join(c for c in cams if has_truth[c])]
            for j, t in enumerate(idx):
                lines.append(f"{t}," + ",".join(f"{ious[c][j]:.5f}" for c in cams if has_truth[c]))
            (tmp / "iou.csv").write_text("\n".join(lines) + "\n")
        (tmp / "summary.json").write_text(json.dumps(summary, indent=2))
        if out_dir.exists():
            shutil.rmtree(out_dir)
        tmp.rename(out_dir)
    except BaseException:
        for wr in writers.values():
            try:
                wr.container.close()
            except Exception:  # already broken: the directory goes anyway
                pass
        shutil.rmtree(tmp, ignore_errors=True)
        for p in reversed(made):
            try:
                p.rmdir()
            except OSError:
                break
        raise
    return summary


# ----------------------------------------------------------------------------- CLI


def _format_summary(summary: dict, out_dir: Path) -> str:
    lines = [f"wrote {out_dir} ({summary['num_frames']} frames, source={summary['source']})",
             f"{'camera':<20} {'size':>9} {'coverage':>9} {'mean IoU':>9} {'min IoU':>8}"]
    for c, e in summary["cameras"].items():
        mean = e.get("mean_iou")
        lo = e.get("min_iou")
        lines.append(f"{c:<20} {e['width']:>4}x{e['height']:<4} {e['mean_rendered_coverage']:>9.3f} "
                     f"{'-' if mean is None else f'{mean:.4f}':>9} {'-' if lo is None else f'{lo:.4f}':>8}")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m imac_data.qa", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("overlay", help="draw the rendered robot outline over an episode's frames")
    p.add_argument("episode", help="raw ALOHA HDF5 episode (episode_N.hdf5)")
    p.add_argument("--calibration", required=True, help="calibration JSON (imac_data.cameras schema)")
    p.add_argument("--out", required=True, help="output directory (must not exist, unless --overwrite)")
    p.add_argument("--robot", default="aloha", choices=sorted(ROBOTS), help="robot description")
    p.add_argument("--recipe", default=None,
                   help="take the robot (your URDF, joint map) from this build recipe instead of --robot")
    p.add_argument("--source", default="state", choices=("state", "action"),
                   help="render the measured state (default) or the commanded actions")
    p.add_argument("--format", default="mp4", choices=("mp4", "png"), dest="fmt")
    p.add_argument("--frames", default=None, help="frame selection START:STOP:STEP (python slice), or one index")
    p.add_argument("--cameras", default=None, help="comma-separated camera names (default: all in the episode)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output directory")
    from imac_data import preview, refine  # preview and refine live in their own modules

    preview.add_command(sub)
    refine.add_arguments(sub.add_parser("refine", help="refine camera poses by aligning the rendered robot "
                                        "with the robot's pixels (README: Fixing a calibration)"))
    args = parser.parse_args(argv)
    from imac_data.cli import run_command

    if args.command == "refine":
        return refine.run(args)
    if args.command == "preview":
        return run_command(lambda: print(preview.run_command(args)))
    return run_command(lambda: _overlay_command(args))


def _overlay_command(args: argparse.Namespace) -> None:
    cams = [c for c in args.cameras.split(",") if c] if args.cameras else None
    robot, controller = args.robot, None
    if args.recipe:
        from imac_data.recipes import load_recipe
        from imac_data.rig import Rig

        rig = Rig.from_recipe(load_recipe(args.recipe), args.calibration)
        robot, controller = rig.robot, rig.controller
    summary = overlay(args.episode, args.calibration, args.out, robot=robot, source=args.source,
                      fmt=args.fmt, frames=args.frames, cameras=cams, overwrite=args.overwrite,
                      controller=controller)
    print(_format_summary(summary, Path(args.out)))


if __name__ == "__main__":
    from imac_data.cli import exit_process

    exit_process(main())
