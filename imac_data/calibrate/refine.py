"""``qa refine``: a calibration refined from the recordings themselves.

The source is raw HDF5 episodes or a LeRobot dataset; the rig comes from a recipe and its
calibration, or from a dataset built by imac. Per camera, frames are chosen, the robot's
pixels taken from the chosen cue, and the pose refined (:mod:`imac_data.calibrate`). It writes
the whole rig as a calibration file with the refined cameras replaced, and a report
directory; neither is ever an input, and both appear only complete. A camera with a time offset
(``time_offset_s``) is fitted with the joint vectors at its images' own time, as the build draws it. A camera whose overlay
would get worse keeps its input pose. ``docs/calibration.md`` has the method and the figures.
"""

from __future__ import annotations

import dataclasses
import math
import os
import time
from collections.abc import Sequence
from pathlib import Path

import torch

from imac_data.calibrate.config import RefineConfig
from imac_data.calibrate.frames import DatasetFrames, RobotPixels, choose_frames, open_frames
from imac_data.calibrate.objective import silhouette_agreement
from imac_data.calibrate.optimise import refine_camera, refine_camera_edges
from imac_data.calibrate.report import camera_entry, draw_overlay, write_outputs
from imac_data.core.cameras import load_calibration
from imac_data.core.render import make_renderer
from imac_data.core.rig import Rig
from imac_data.dataset.output import check_replaceable, refuse_overlap
from imac_data.errors import InputError
from imac_data.metadata import imac_block_path
from imac_data.recipes import load_recipe

__all__ = ["refine_calibration"]


def _check_outputs(out: Path, report: Path, inputs: dict, overwrite: bool) -> None:
    for path, what in ((out, "--out"), (report, "--report")):
        for name, p in inputs.items():
            if p is not None and p.exists() and path.resolve() == p.resolve():
                raise InputError(f"{what} {path} is the {name}: the input is never overwritten; choose another name")
        refuse_overlap(path, inputs, what=what)
        if path.exists() and not overwrite:
            raise InputError(f"{what} {path} exists; pass --overwrite to replace it")
    if out.is_dir():
        raise InputError(f"--out {out} is a directory; give a file name such as refined.json")
    check_replaceable(report, made_by="report.json", what="--report")


def _rig(src, recipe, calibration: Path | None):
    """The rig, the calibration file it was made from (``None``: the dataset's own) and the recording's frame rate
    (the recipe's fps, else the source's)."""
    fps = getattr(src, "fps", None)
    if recipe is None:
        if not isinstance(src, DatasetFrames):
            raise InputError("--recipe is required for raw episodes (the robot and its cameras); only a dataset "
                             "built by imac carries its rig")
        rig = Rig.from_dataset(src.source)
        if calibration is not None:
            rig = Rig(rig.robot, load_calibration(calibration), rig.controller, rig.state_names,
                      rig.gripper_spacing)
        return rig, calibration, fps
    recipe = load_recipe(recipe) if isinstance(recipe, (str, Path)) else recipe
    if calibration is None:
        calibration = recipe.resolve_path(recipe.cameras.calibration)
        if calibration is None:
            raise InputError(f"{recipe.file or 'recipe'}: no calibration given (--calibration, or the recipe's "
                             "cameras.calibration)")
    fps = recipe.fps if recipe.fps is not None else fps
    return Rig.from_recipe(recipe, calibration), Path(calibration), fps  # mounted cameras' links checked


def refine_calibration(source: str | Path, out: str | Path, *, recipe=None, calibration: str | Path | None = None,
                       robot_pixels: str = "auto", cameras: Sequence[str] | None = None, frames: int = 8,
                       min_separation: float = 0.1, config: RefineConfig | None = None, near: float = 0.0,
                       report: str | Path | None = None, overwrite: bool = False, edge_rounds: int = 3,
                       edge_margin: float = 0.08, candidate_budget: int = 400, log=None) -> dict:
    """Refine the calibration of a rig from the frames in ``source``; write ``out`` and the
    report directory; return the report dict. The rig: ``recipe`` (a path or a loaded recipe)
    with ``calibration`` (default: the recipe's), or a built dataset's own. Every input is
    checked before any work."""
    log = log or (lambda msg: None)
    config = config or RefineConfig()
    source, out = Path(source), Path(out)
    report = Path(report) if report is not None else out.with_name(out.stem + ".report")
    calibration = Path(calibration) if calibration is not None else None
    if frames < 3:
        raise InputError(f"--frames must be at least 3 (got {frames}): one or two views hardly constrain a pose")
    if not (math.isfinite(near) and near >= 0):
        raise InputError(f"--near must be >= 0 metres, got {near}")
    recipe_path = Path(recipe) if isinstance(recipe, (str, Path)) else getattr(recipe, "file", None)
    inputs = {"source": source, "calibration": calibration, "recipe": Path(recipe_path) if recipe_path else None}
    _check_outputs(out, report, inputs, overwrite)
    src = open_frames(source)
    rig, calibration, fps = _rig(src, recipe, calibration)
    if calibration is not None and inputs["calibration"] is None:  # the recipe's calibration is an input too
        _check_outputs(out, report, {**inputs, "calibration": calibration}, overwrite)
    cams = list(cameras) if cameras else [c for c in src.cameras if c in rig.cameras]
    missing = [c for c in cams if c not in src.cameras]
    if missing:
        raise InputError(f"{source}: camera(s) {missing} not in the source (it has {src.cameras})")
    where = calibration or str(imac_block_path(source))
    uncalibrated = [c for c in cams if c not in rig.cameras]
    if uncalibrated:
        raise InputError(f"{where}: no calibration for camera(s) {uncalibrated} (calibrated: {sorted(rig.cameras)})")
    if not cams:
        raise InputError(f"no camera is both in the source ({src.cameras}) and calibrated ({sorted(rig.cameras)})")
    offsets = {c: rig.cameras[c].time_offset_s for c in cams if rig.cameras[c].time_offset_s}
    if offsets and not fps:
        raise InputError(f"{where}: camera time offsets {offsets} s need the recording's frame rate, which neither "
                         f"the recipe (fps) nor {source} gives: set fps in the recipe")
    dof = src.joints(src.episodes[0]).shape[1]
    if dof != rig.dof:
        raise InputError(f"{source}: joint vectors have {dof} entries, robot {rig.robot.name!r} expects {rig.dof}")
    pixels = RobotPixels.parse(robot_pixels, src)
    sized = rig.with_image_sizes({c: src.image_hw(c) for c in cams}).cameras  # calibration at the frames' size
    if near > 0:
        renderer = make_renderer(rig.robot, near=near, nthreads=rig.threads)
    else:
        renderer = rig.renderer

    t0, c0 = time.perf_counter(), time.process_time()
    result = {"source": str(source), "calibration": str(where), "out": str(out), "robot": rig.robot.name,
              "robot_urdf_sha256": rig.robot.urdf_hash, "robot_pixels": str(pixels), "near_m": near,
              "config": config.to_dict(), "cameras": {}}
    refined, overlays = dict(rig.cameras), {}
    edges = pixels.kind == "edges"
    for c in cams:
        log(f"[refine] {c}: choosing frames")
        cam0 = sized[c]
        chosen = choose_frames(src, cam0, renderer, pixels, frames, min_separation=min_separation,
                               budget=candidate_budget, shift=offsets.get(c, 0.0) * (fps or 0.0))  # its own time
        log(f"[refine] {c}: frames {[f'{Path(e).stem}:{t}' for e, t in chosen.refs]}")
        if edges:
            fit, chosen.target = refine_camera_edges(renderer, cam0, chosen.q, chosen.images, config,
                                                     rounds=edge_rounds, margin=edge_margin, log=log)
        else:
            fit = refine_camera(renderer, cam0, chosen.q, chosen.target, config, log=log)
        q = torch.as_tensor(chosen.q)
        before = renderer.render(q, {c: cam0})[c].mask.numpy()
        after = renderer.render(q, {c: fit.camera})[c].mask.numpy()
        agree0 = silhouette_agreement(before, chosen.target, edges=edges)
        agree1 = silhouette_agreement(after, chosen.target, edges=edges)
        original = rig.cameras[c]
        new = fit.camera.rescaled(original.width, original.height) \
            if (fit.camera.height, fit.camera.width) != (original.height, original.width) else fit.camera
        new = dataclasses.replace(new, time_offset_s=original.time_offset_s)  # refine moves the pose only
        score = "boundary_px" if edges else "iou"
        kept = not (agree1[score] <= agree0[score] if edges else agree1[score] >= agree0[score])
        if kept:  # never hand back a worse calibration
            log(f"[refine] {c}: refinement did not improve the overlay ({score} {agree0[score]:.4f} -> "
                f"{agree1[score]:.4f}); keeping the input calibration for this camera")
            new, after, agree1 = original, before, agree0
        refined[c] = new
        result["cameras"][c] = camera_entry(original, new, agree0, agree1, refs=chosen.refs, kept=kept, fit=fit)
        result["cameras"][c]["time_offset_s"] = original.time_offset_s  # the joints fitted: those of t + offset
        overlays[c] = tuple(draw_overlay(chosen.images, m, chosen.target, f"{c} {when}: " + (
            f"outline {a['boundary_px']:.2f} px from the edges" if edges else f"IoU {a['iou']:.4f}"), edges=edges)
            for when, m, a in (("before", before, agree0), ("after", after, agree1)))
    result["wall_s"] = time.perf_counter() - t0
    result["cpu_s"] = time.process_time() - c0
    result["load_avg"] = list(os.getloadavg())
    result["report"] = str(report)
    write_outputs(out, report, refined, result, overlays)
    return result
