"""``imac qa overlay | calibrate | refine | preview``: look at a calibration, make one from nothing, fix it, look at a
built episode."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from imac_data.calibrate.config import RefineConfig
from imac_data.calibrate.from_nothing import calibrate_from_nothing, format_calibration_report
from imac_data.calibrate.refine import refine_calibration
from imac_data.calibrate.report import format_report
from imac_data.calibrate.scratch import ScratchConfig
from imac_data.console import run_command
from imac_data.core.rig import Rig
from imac_data.qa.overlay import format_summary, overlay
from imac_data.qa.preview import write_preview
from imac_data.recipes import load_recipe


def run(args: argparse.Namespace) -> int:
    body = {"overlay": _overlay, "refine": _refine, "calibrate": _calibrate, "preview": _preview}[args.qa_command]
    return run_command(lambda: body(args))


def _overlay(args: argparse.Namespace) -> None:
    cams = [c for c in args.cameras.split(",") if c] if args.cameras else None
    robot, controller, fps = args.robot, None, None
    if args.recipe:
        recipe = load_recipe(args.recipe)
        rig = Rig.from_recipe(recipe, args.calibration)
        robot, controller, fps = rig.robot, rig.controller, recipe.fps
    summary = overlay(args.episode, args.calibration, args.out, robot=robot, source=args.source, fmt=args.fmt,
                      frames=args.frames, cameras=cams, overwrite=args.overwrite, controller=controller, fps=fps)
    print(format_summary(summary, Path(args.out)))


def _refine(args: argparse.Namespace) -> None:
    over = {}
    if args.method:
        over["method"] = args.method
    if args.refine_focal:
        over["refine_focal"] = True
    cams = [c for c in args.cameras.split(",") if c] if args.cameras else None
    result = refine_calibration(args.source, args.out, recipe=args.recipe, calibration=args.calibration,
                                robot_pixels=args.robot_pixels, cameras=cams, frames=args.frames,
                                min_separation=args.min_separation, config=RefineConfig(**over), near=args.near,
                                report=args.report, overwrite=args.overwrite, log=lambda m: print(m, file=sys.stderr))
    print(format_report(result))


def _calibrate(args: argparse.Namespace) -> None:
    cams = [c for c in args.cameras.split(",") if c] if args.cameras else None
    summary = calibrate_from_nothing(
        args.source, args.out, recipe=args.recipe, cameras=cams, mounts=dict(args.mount), fov=dict(args.fov),
        intrinsics=args.intrinsics, depth=args.depth, da3_model=args.da3_model,
        estimate_depth_scale=args.estimate_depth_scale,
        config=ScratchConfig(frames=args.frames), candidates=args.candidates, refine=args.refine, near=args.near,
        report=args.report, overwrite=args.overwrite, time_offset_window=args.max_time_offset / 1000.0,
        progress=not args.no_progress, log=lambda m: print(m, file=sys.stderr))
    print(format_calibration_report(summary))


def _preview(args: argparse.Namespace) -> None:
    path = write_preview(args.root, args.episode, args.out, depth_max=args.depth_max, overwrite=args.overwrite,
                         progress=not args.no_progress)
    print(f"wrote {path}")
