"""``qa refine``: fix a calibration from the recordings themselves.

    python -m imac_data.qa refine SOURCE --recipe R.yaml [--calibration calib.json] --out refined.json
        [--robot-pixels auto|sim|edges|MASK_DIR] [--cameras cam_high,...] [--frames 8]
        [--method gradient|nelder-mead|powell] [--refine-focal] [--near METRES]
        [--report DIR] [--overwrite]

The rig (robot, cameras, controller, renderer) comes from the recipe and the calibration
(:meth:`imac_data.rig.Rig.from_recipe`; ``--calibration`` defaults to the recipe's
``cameras.calibration``). SOURCE is a directory of raw ALOHA/AgileX HDF5 episodes or one
episode file, read through :class:`imac_data.calibrate.EpisodeFrames`. Per camera, frames
are chosen, the robot's pixels taken from the chosen source
(:class:`imac_data.calibrate.RobotPixels`) and the pose refined
(:mod:`imac_data.calibrate`). It writes

* ``refined.json``: the whole rig in the README's calibration format (checked by loading it
  back with :func:`imac_data.cameras.load_calibration`), the refined cameras replaced. It is
  never the input file: an output that is, contains or lies inside an input (episodes,
  calibration, recipe) is refused before any work (:func:`imac_data.safety.refuse_overlap`);
* the report directory (default ``refined.report/`` beside it, :mod:`imac_data.calibrate.report`).

Both appear only complete (temporary names, renamed at the end). A camera whose overlay
would get worse keeps its input pose.

``--near`` is the renderer's near clip plane in metres, 0 by default (real cameras do not
clip). Simulator masks are clipped at the simulator's near plane (gym-aloha: ``znear *
extent`` = 0.166 m), so for simulated episodes pass that value: a gripper closer to its
wrist camera than that is missing from the masks, and rendering it would bias the wrist
cameras.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import torch

from imac_data.calibrate import (EpisodeFrames, RefineConfig, RobotPixels, choose_frames, refine_camera,
                                 refine_camera_edges, silhouette_agreement)
from imac_data.calibrate.report import camera_entry, draw_overlay, format_report, write_outputs
from imac_data.errors import InputError

__all__ = ["refine_calibration", "add_arguments", "run", "main"]


def _check_outputs(out: Path, report: Path, inputs: dict, overwrite: bool) -> None:
    from imac_data.safety import refuse_overlap

    for path, what in ((out, "--out"), (report, "--report")):
        for name, p in inputs.items():
            if p is not None and p.exists() and path.resolve() == p.resolve():
                raise InputError(f"{what} {path} is the {name}: the input is never overwritten; choose another name")
        refuse_overlap(path, inputs, what=what)
        if path.exists() and not overwrite:
            raise InputError(f"{what} {path} exists; pass --overwrite to replace it")
    if out.is_dir():
        raise InputError(f"--out {out} is a directory; give a file name such as refined.json")


def refine_calibration(source: str | Path, out: str | Path, *, recipe, calibration: str | Path | None = None,
                       robot_pixels: str = "auto", cameras: Sequence[str] | None = None, frames: int = 8,
                       min_separation: float = 0.1, config: RefineConfig | None = None, near: float = 0.0,
                       report: str | Path | None = None, overwrite: bool = False, edge_rounds: int = 3,
                       edge_margin: float = 0.08, candidate_budget: int = 400, log=None) -> dict:
    """Refine the calibration of the rig that ``recipe`` (a path or a loaded recipe) and
    ``calibration`` describe from the episodes in ``source``; write ``out`` and the report
    directory; return the report dict. Every input is checked before any work."""
    from imac_data.recipes import load_recipe
    from imac_data.rig import Rig

    log = log or (lambda msg: None)
    config = config or RefineConfig()
    source, out = Path(source), Path(out)
    report = Path(report) if report is not None else out.with_name(out.stem + ".report")
    if frames < 3:
        raise InputError(f"--frames must be at least 3 (got {frames}): one or two views hardly constrain a pose")
    if not (math.isfinite(near) and near >= 0):
        raise InputError(f"--near must be >= 0 metres, got {near}")
    recipe_path = Path(recipe) if isinstance(recipe, (str, Path)) else getattr(recipe, "file", None)
    recipe = load_recipe(recipe) if isinstance(recipe, (str, Path)) else recipe
    if calibration is None:
        calibration = recipe.resolve_path(recipe.cameras.calibration)
        if calibration is None:
            raise InputError(f"{recipe_path or 'recipe'}: no calibration given (--calibration, or the recipe's "
                             "cameras.calibration)")
    calibration = Path(calibration)
    _check_outputs(out, report, {"source episodes": source, "calibration": calibration,
                                 "recipe": Path(recipe_path) if recipe_path else None}, overwrite)
    rig = Rig.from_recipe(recipe, calibration)  # mounted cameras' links checked against the URDF
    src = EpisodeFrames(source)
    cams = list(cameras) if cameras else [c for c in src.cameras if c in rig.cameras]
    missing = [c for c in cams if c not in src.cameras]
    if missing:
        raise InputError(f"{source}: camera(s) {missing} not in the episodes (they have {src.cameras})")
    uncalibrated = [c for c in cams if c not in rig.cameras]
    if uncalibrated:
        raise InputError(f"{calibration}: no calibration for camera(s) {uncalibrated} "
                         f"(calibrated: {sorted(rig.cameras)})")
    if not cams:
        raise InputError(f"no camera is both in the episodes ({src.cameras}) and calibrated ({sorted(rig.cameras)})")
    dof = src.joints(src.episodes[0]).shape[1]
    if dof != rig.dof:
        raise InputError(f"{src.episodes[0]}: joint vectors have {dof} entries, robot {rig.robot.name!r} "
                         f"expects {rig.dof}")
    pixels = RobotPixels.parse(robot_pixels, src)
    sized = rig.with_image_sizes({c: src.image_hw(c) for c in cams}).cameras  # calibration at the frames' size
    if near > 0:
        from imac_data.render import make_renderer

        renderer = make_renderer(rig.robot, near=near, nthreads=rig.threads)
    else:
        renderer = rig.renderer

    t0, c0 = time.perf_counter(), time.process_time()
    result = {"source": str(source), "calibration": str(calibration), "out": str(out), "robot": rig.robot.name,
              "robot_urdf_sha256": rig.robot.urdf_hash, "robot_pixels": str(pixels), "near_m": near,
              "config": config.to_dict(), "cameras": {}}
    refined, overlays = dict(rig.cameras), {}
    edges = pixels.kind == "edges"
    for c in cams:
        log(f"[refine] {c}: choosing frames")
        cam0 = sized[c]
        chosen = choose_frames(src, cam0, renderer, pixels, frames, min_separation=min_separation,
                               budget=candidate_budget)
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
        score = "boundary_px" if edges else "iou"
        kept = not (agree1[score] <= agree0[score] if edges else agree1[score] >= agree0[score])
        if kept:  # never hand back a worse calibration
            log(f"[refine] {c}: refinement did not improve the overlay ({score} {agree0[score]:.4f} -> "
                f"{agree1[score]:.4f}); keeping the input calibration for this camera")
            new, after, agree1 = original, before, agree0
        refined[c] = new
        result["cameras"][c] = camera_entry(original, new, agree0, agree1, refs=chosen.refs, kept=kept, fit=fit)
        overlays[c] = tuple(draw_overlay(chosen.images, m, chosen.target, f"{c} {when}: " + (
            f"outline {a['boundary_px']:.2f} px from the edges" if edges else f"IoU {a['iou']:.4f}"), edges=edges)
            for when, m, a in (("before", before, agree0), ("after", after, agree1)))
    result["wall_s"] = time.perf_counter() - t0
    result["cpu_s"] = time.process_time() - c0
    result["load_avg"] = list(os.getloadavg())
    result["report"] = str(report)
    write_outputs(out, report, refined, result, overlays)
    return result


# ----------------------------------------------------------------------------- CLI


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("source", help="directory of raw HDF5 episodes, or one episode file")
    p.add_argument("--recipe", required=True, help="build recipe: the robot (URDF, joint map) and its cameras")
    p.add_argument("--calibration", default=None,
                   help="calibration JSON to refine (never modified; default: the recipe's cameras.calibration)")
    p.add_argument("--out", required=True, help="refined calibration JSON to write")
    p.add_argument("--robot-pixels", default="auto",
                   help="where the robot's pixels come from: auto (default: sim if recorded, else edges), sim, "
                        "edges, or a mask directory DIR/<episode stem>/<camera>/<frame:06d>.png")
    p.add_argument("--cameras", default=None, help="comma-separated cameras (default: every calibrated one)")
    p.add_argument("--frames", type=int, default=8, help="frames per camera (default 8)")
    p.add_argument("--min-separation", type=float, default=0.1,
                   help="smallest joint-space distance between chosen frames (default 0.1)")
    p.add_argument("--method", default=None, help="gradient (default), nelder-mead or powell")
    p.add_argument("--refine-focal", action="store_true", help="also refine the focal length")
    p.add_argument("--near", type=float, default=0.0,
                   help="renderer near clip plane in metres (default 0; simulated episodes: the simulator's)")
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
        result = refine_calibration(args.source, args.out, recipe=args.recipe, calibration=args.calibration,
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
