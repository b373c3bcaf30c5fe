"""The report of a refinement: per camera the overlay before and after (IoU with the robot's
pixels, outline distance in px), the pose change per axis, and the overlay images.

``report.json`` holds, per camera, the frames used, ``iou_before``/``iou_after`` (mean binary
IoU with the robot pixels; ``None`` with the edge cue, which has no robot mask),
``boundary_px_before``/``_after`` (mean distance between the rendered and the observed
outlines, :func:`~imac_data.calibrate.objective.silhouette_agreement`), the pose change in
the camera's own axes (mm, degrees), the focal change, renders and time.
``{camera}_before.png`` / ``{camera}_after.png`` show the chosen frames with the rendered
robot's outline in green over the robot pixels' outline (or the edges the cue found) in magenta.
"""

from __future__ import annotations

import json
import shutil
import tempfile
from pathlib import Path

import cv2
import numpy as np

from imac_data.calibrate.pose import AXES, pose_change
from imac_data.core.cameras import Camera, load_calibration, save_calibration
from imac_data.core.masks import outline

__all__ = ["OUTLINE_RGB", "TARGET_RGB", "draw_overlay", "camera_entry", "format_report", "write_outputs"]

OUTLINE_RGB = (0, 255, 0)  # rendered robot
TARGET_RGB = (255, 0, 255)  # robot pixels


def draw_overlay(images: np.ndarray, rendered: np.ndarray, target: np.ndarray, title: str, *,
                 edges: bool = False) -> np.ndarray:
    """A grid of the frames (at most 8, four per row), with the outline of the robot pixels
    (or the edge pixels themselves, ``edges=True``) and of the render."""
    tiles = []
    for img, r, g in zip(images[:8], rendered[:8], target[:8]):
        t = max(1, round(img.shape[0] / 240))
        out = img.copy()
        out[g > 0 if edges else outline(g >= 0.5, t)] = TARGET_RGB
        out[outline(r, t)] = OUTLINE_RGB
        tiles.append(out)
    while len(tiles) % 4 and len(tiles) > 4:
        tiles.append(np.zeros_like(tiles[0]))
    grid = np.concatenate([np.concatenate(tiles[i:i + 4], 1) for i in range(0, len(tiles), 4)], 0)
    scale = min(1.0, 1600 / grid.shape[1])
    if scale < 1:
        grid = cv2.resize(grid, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
    for colour, width in (((0, 0, 0), 4), ((255, 255, 255), 1)):
        cv2.putText(grid, title, (8, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.7, colour, width, cv2.LINE_AA)
    return grid


def camera_entry(calibrated: Camera, refined: Camera, before: dict, after: dict, *, refs, kept: bool,
                 fit) -> dict:
    """One camera's ``report.json`` entry (``before``/``after``: silhouette agreements)."""
    return {
        "mounted_on": calibrated.link, "frames": [[e, t] for e, t in refs], "kept_input": kept,
        "iou_before": before["iou"], "iou_after": after["iou"],
        "iou_per_frame_before": before["iou_per_frame"], "iou_per_frame_after": after["iou_per_frame"],
        "boundary_px_before": before["boundary_px"], "boundary_px_after": after["boundary_px"],
        "pose_change": pose_change(calibrated, refined),
        "focal_change_pct": 100.0 * (refined.K[0, 0] / calibrated.K[0, 0] - 1.0),
        "renders": fit.renders, "wall_s": fit.wall_s, "cpu_s": fit.cpu_s,
    }


def format_report(result: dict) -> str:
    """The table ``qa refine`` prints."""
    lines = [f"wrote {result['out']} and {result['report']}/ (robot pixels: {result['robot_pixels']}, "
             f"{result['wall_s']:.0f} s wall, {result['cpu_s']:.0f} s CPU, load {result['load_avg'][0]:.1f})",
             f"{'camera':<18} {'IoU before':>10} {'after':>7} {'bdry px':>8} {'after':>6}  "
             + " ".join(f"{a.replace('_', ' '):>7}" for a in AXES)]

    def iou(x):
        return "-" if x is None else f"{x:.4f}"

    for c, e in result["cameras"].items():
        p = e["pose_change"]
        lines.append(f"{c:<18} {iou(e['iou_before']):>10} {iou(e['iou_after']):>7} {e['boundary_px_before']:>8.2f} "
                     f"{e['boundary_px_after']:>6.2f}  " + " ".join(f"{p[k]:>7.2f}" for k in AXES)
                     + ("  (kept the input)" if e["kept_input"] else ""))
    lines.append("pose change in each camera's own axes (x right, y down, z forward); bdry px = mean distance "
                 "between the rendered and the observed outlines (edges cue: to the nearest image edge)")
    return "\n".join(lines)


def write_outputs(out: Path, report: Path, cameras: dict[str, Camera], result: dict,
                  overlays: dict[str, tuple[np.ndarray, np.ndarray]]) -> None:
    """Write the calibration ``out`` (the format of docs/calibration.md, checked by loading it back) and the
    report directory. Both appear only complete: temporary names beside them, renamed at the end."""
    out, report = Path(out), Path(report)
    out.parent.mkdir(parents=True, exist_ok=True)
    report.parent.mkdir(parents=True, exist_ok=True)
    tmp_json = out.with_name(f".{out.name}.tmp")
    tmp_dir = Path(tempfile.mkdtemp(prefix=f".{report.name}.", dir=report.parent))
    try:
        save_calibration(tmp_json, cameras)
        load_calibration(tmp_json)  # the calibration parser accepts what we wrote
        for c, (b, a) in overlays.items():
            cv2.imwrite(str(tmp_dir / f"{c}_before.png"), b[..., ::-1])
            cv2.imwrite(str(tmp_dir / f"{c}_after.png"), a[..., ::-1])
        (tmp_dir / "report.json").write_text(json.dumps(result, indent=2))
        if report.exists():
            shutil.rmtree(report)
        tmp_dir.rename(report)
        tmp_json.replace(out)
    except BaseException:
        tmp_json.unlink(missing_ok=True)
        shutil.rmtree(tmp_dir, ignore_errors=True)
        raise
