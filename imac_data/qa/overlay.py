"""The calibration check: the rendered robot's outline drawn over an episode's real frames.

Per camera an mp4 (or PNGs), with the ground-truth outline and the per-frame mask IoU where
the episode carries a robot segmentation (simulated episodes), and a ``summary.json``. The
output directory appears only complete. ``--source action`` renders what the motion images
show, which lags the images by the controller's tracking delay. A camera with a time offset
(``time_offset_s`` in the calibration) is drawn at its image's own time, as the build draws it.
"""

from __future__ import annotations

import json
import shutil
import tempfile
from collections.abc import Sequence
from fractions import Fraction
from pathlib import Path

import av
import cv2
import numpy as np
import torch

from imac_data.core.cameras import load_calibration
from imac_data.core.masks import ground_truth_robot_mask, mask_iou, outline
from imac_data.core.motion import SOURCES, frame_configurations, joints_at
from imac_data.core.render import make_renderer
from imac_data.core.rig import Rig
from imac_data.core.robot.model import RobotModel
from imac_data.core.robot.platforms import PLATFORMS, platform
from imac_data.dataset.output import check_replaceable
from imac_data.errors import InputError
from imac_data.sources.hdf5 import read_episode

__all__ = ["overlay", "format_summary"]

OUTLINE_RGB = (0, 255, 0)  # rendered robot
TRUTH_RGB = (255, 0, 255)  # ground-truth robot mask
DEFAULT_FPS = 50.0  # ALOHA's recording rate, for an episode without an 'fps' attribute and no fps given



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
        self.container = av.open(str(path), mode="w")
        self.stream = self.container.add_stream("libx264", rate=Fraction(fps).limit_denominator(1000))
        self.stream.width, self.stream.height = width + width % 2, height + height % 2
        self.stream.pix_fmt = "yuv420p"
        self.stream.options = {"crf": "18", "preset": "veryfast"}
        
    def write(self, rgb: np.ndarray) -> None:
        h, w = self.stream.height, self.stream.width
        if rgb.shape[:2] != (h, w):
            rgb = np.pad(rgb, ((0, h - rgb.shape[0]), (0, w - rgb.shape[1]), (0, 0)))
        frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(rgb), format="rgb24")
        for packet in self.stream.encode(frame):
            self.container.mux(packet)

    def close(self) -> None:
        for packet in self.stream.encode():
            self.container.mux(packet)
        self.container.close()


def _configurations_at_camera_times(q: np.ndarray, offsets: dict[str, float], fps: float) -> dict[float, np.ndarray]:
    """Per distinct time offset, the configurations ``q`` ``(T, D)`` at each frame's time plus the offset, as the
    build draws a camera (:func:`~imac_data.core.motion.joints_at`: Catmull-Rom, clamped at the episode's ends; an offset
    of 0 keeps ``q`` itself)."""
    frames = np.arange(len(q), dtype=np.float64)
    return {d: q if d == 0 else joints_at(q, frames + d * fps) for d in dict.fromkeys(offsets.values())}


# ----------------------------------------------------------------------------- overlay


def overlay(episode_path: str | Path, calibration_path: str | Path, out_dir: str | Path, *,
            robot: str | RobotModel | None = None, source: str = "state", fmt: str = "mp4", frames: str | None = None,
            cameras: Sequence[str] | None = None, overwrite: bool = False, batch: int = 8,
            renderer=None, controller=None, fps: float | None = None) -> dict:
    """Write the overlay of one episode into ``out_dir`` and return the summary dict.

    ``robot``: a registered platform's name (:data:`~imac_data.core.robot.platforms.PLATFORMS`;
    default the first) or a :class:`~imac_data.core.robot.model.RobotModel`.
    The video's rate is ``fps`` (a recipe's, as the build takes it), else the episode's ``fps`` attribute,
    else :data:`DEFAULT_FPS`; the summary says which (``fps_from``).
    All inputs are validated before anything is written; the output directory appears
    only complete (temporary sibling renamed into place).
    """
    episode_path, out_dir = Path(episode_path), Path(out_dir)
    if fmt not in ("mp4", "png"):
        raise InputError(f"--format must be mp4 or png, got {fmt!r}")
    if source not in SOURCES:
        raise InputError(f"--source must be one of {SOURCES}, got {source!r}")
    if fps is not None and not 0 < fps < float("inf"):
        raise InputError(f"fps must be a positive number, got {fps}")
    if out_dir.exists() and not overwrite:
        raise InputError(f"output {out_dir} exists; pass --overwrite to replace it")
    check_replaceable(out_dir, made_by="summary.json", what="output")
    calib = load_calibration(calibration_path)
    platform_name = None
    if robot is None or isinstance(robot, str):
        platform_name = robot if robot is not None else next(iter(PLATFORMS))
        robot = RobotModel(platform(platform_name, "--robot").robot())
    elif not isinstance(robot, RobotModel):
        raise InputError(f"robot must be a platform in {sorted(PLATFORMS)} or a RobotModel, got {type(robot).__name__}")
    robot_name = robot.name
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
    if controller is None and source == "action" and platform_name is not None:
        controller = Rig.from_platform(platform_name, rig, robot=robot).controller
    kwargs = {} if controller is None else {"controller": controller}
    q_all = frame_configurations(ep.qpos, ep.action, source=source, **kwargs)
    robot.joint_positions(torch.as_tensor(q_all))  # wrong length / non-finite -> InputError now
    sel = _parse_frames(frames, ep.num_frames)
    truth_links = renderer.link_names
    has_truth = {c: c in ep.segmentation and bool(ep.segmentation_labels) for c in cams}
    if fps is not None:  # the recipe's, as the build takes it: the user's word on the recording
        episode_fps, fps_from = float(fps), "recipe"
    elif ep.fps is not None:
        episode_fps, fps_from = ep.fps, "episode"
    else:
        episode_fps, fps_from = DEFAULT_FPS, "default"
    offsets = {c: rig[c].time_offset_s for c in cams}
    if any(offsets.values()) and fps_from == "default":
        raise InputError(f"{calibration_path}: camera time offsets {({c: d for c, d in offsets.items() if d})} s need "
                         f"the recording's frame rate, and {episode_path} has no 'fps' attribute: pass --recipe with "
                         "its fps")
    q_cam = _configurations_at_camera_times(q_all, offsets, episode_fps)
    fps = episode_fps / sel.step

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
            views = {}
            for group in dict.fromkeys(offsets.values()):  # the cameras of one offset render together
                views.update(renderer.render(torch.as_tensor(q_cam[group][chunk]),
                                             {c: rig[c] for c in cams if offsets[c] == group}))
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
            "episode_fps": episode_fps, "fps_from": fps_from,
            "cameras": {},
        }
        for c in cams:
            entry = {"width": rig[c].width, "height": rig[c].height, "time_offset_s": offsets[c],
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


_FPS_FROM = {"episode": "the episode's 'fps' attribute",
             "recipe": "the recipe's fps",
             "default": "the default (the episode has no 'fps' attribute; set fps in a recipe and pass --recipe)"}


def format_summary(summary: dict, out_dir: Path) -> str:
    step = summary["frames"][2]
    lines = [f"wrote {out_dir} ({summary['num_frames']} frames, source={summary['source']})",
             f"fps {summary['episode_fps']:g} from {_FPS_FROM[summary['fps_from']]}"
             + (f"; one frame in {step}, so the videos play at {summary['fps']:g}" if step > 1 else ""),
             f"{'camera':<20} {'size':>9} {'coverage':>9} {'mean IoU':>9} {'min IoU':>8}"]
    for c, e in summary["cameras"].items():
        mean = e.get("mean_iou")
        lo = e.get("min_iou")
        lines.append(f"{c:<20} {e['width']:>4}x{e['height']:<4} {e['mean_rendered_coverage']:>9.3f} "
                     f"{'-' if mean is None else f'{mean:.4f}':>9} {'-' if lo is None else f'{lo:.4f}':>8}")
    return "\n".join(lines)
