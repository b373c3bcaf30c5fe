"""The one parser of the ``imac`` command line. It imports nothing heavy, so ``--help`` and
Ctrl-C while a command loads stay instant; each command's body is its module's ``run(args)``."""

from __future__ import annotations

import argparse
from pathlib import Path

from imac_data.core.robot.lerobot_units import LEROBOT_ARMS, UNITS

__all__ = ["build_parser", "COMMANDS"]

# command -> the module whose run(args) carries it out
COMMANDS = {
    "build": "imac_data.cli.build",
    "augment": "imac_data.cli.augment",
    "validate": "imac_data.cli.validate",
    "qa overlay": "imac_data.cli.qa",
    "qa refine": "imac_data.cli.qa",
    "qa calibrate": "imac_data.cli.qa",
    "qa preview": "imac_data.cli.qa",
    "simulate": "imac_data.cli.simulate",
    "robot joints": "imac_data.cli.robot",
}
TASKS = ("transfer_cube", "insertion", "lift")


def _package_dir(text: str) -> tuple[str, str]:
    name, sep, path = text.partition("=")
    if not sep or not name or not path:
        raise argparse.ArgumentTypeError(f"expected NAME=PATH, got {text!r}")
    return name, path


def _build(p: argparse.ArgumentParser) -> None:
    p.add_argument("--repo", required=True, help="dataset repo id, e.g. local/aloha_sim_transfer_cube")
    p.add_argument("--recipe", type=Path, help="recipe YAML (default: recipes/<name of --repo>.yaml)")
    p.add_argument("--root", type=Path, help="output directory (default: $HF_LEROBOT_HOME/<repo>)")
    p.add_argument("--source", type=Path, help="directory of raw episodes (overrides the recipe's source.path)")
    p.add_argument("--episodes", type=int, help="use the first N episodes (overrides the recipe)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output dataset")
    p.add_argument("--workers", type=int,
                   help="parallel episode workers, each pinned to its share of the cores (default: one per core, "
                        "at most one per episode)")
    p.add_argument("--executor", choices=("local", "ray"), default="local",
                   help="local process pool (default) or Ray tasks")
    p.add_argument("--ray-address", help="Ray cluster address (default: start a local Ray)")
    p.add_argument("--push-to-hub", action="store_true",
                   help="upload the result with LeRobot's push_to_hub (needs `huggingface-cli login`)")
    p.add_argument("--private", action="store_true", help="with --push-to-hub: a private dataset repo")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.add_argument("--timings", type=Path, help="write the build's stage timings (JSON) here as well")
    p.add_argument("--wait", action="store_true",
                   help="if another build is writing the same output, wait for it (default: refuse, exit 3)")
    p.add_argument("--device", default="cpu",
                   help="where the robot is rendered and contact painted: cpu (default: Open3D ray casting, KD-trees) "
                        "or cuda / cuda:N (a torch rasteriser and brute-force contact on that GPU; docs/building.md, "
                        "'The GPU path')")


def _augment(p: argparse.ArgumentParser) -> None:
    p.add_argument("--repo", required=True, help="dataset repo id (looked up under $HF_LEROBOT_HOME unless --root)")
    p.add_argument("--root", type=Path, help="dataset directory")
    p.add_argument("--recipe", type=Path, required=True, help="recipe YAML: robot, calibration, augment settings")
    p.add_argument("--source", type=Path, required=True, help="raw HDF5 episodes of the dataset (recorded depth)")
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("--device", default="cpu", help="as imac build's: cpu (default) or cuda / cuda:N")


def _validate(p: argparse.ArgumentParser) -> None:
    checks = ("metadata", "frame_counts", "imac_block", "rig", "joint_units", "calibration", "caps", "decode", "depth")
    p.add_argument("root", type=Path, help="dataset directory")
    p.add_argument("--full", action="store_true", help="decode every frame of every video (default: samples)")
    p.add_argument("--sample", type=int, default=4, help="frames sampled per episode (default 4)")
    p.add_argument("--check", action="append", choices=checks, help="run only this check (repeatable)")
    p.add_argument("--restore-imac-from", type=Path, metavar="ORIGINAL",
                   help="first put back the imac block and robot description (meta/imac/) that a tool writing a "
                        "new dataset left out, from ORIGINAL, the imac-built dataset it was made from (docs/lerobot.md)")


def _overlay(p: argparse.ArgumentParser) -> None:
    p.add_argument("episode", help="raw ALOHA HDF5 episode (episode_N.hdf5)")
    p.add_argument("--calibration", required=True, help="calibration JSON")
    p.add_argument("--out", required=True, help="output directory (must not exist, unless --overwrite)")
    p.add_argument("--robot", default=None, help="a built-in robot platform (default: the first registered)")
    p.add_argument("--recipe", default=None,
                   help="take the robot (your URDF, joint map) from this build recipe instead of --robot, and "
                        "its fps (as the build: else the episode's 'fps' attribute, else 50)")
    p.add_argument("--source", default="state", choices=("state", "action"),
                   help="render the measured state (default) or the commanded actions")
    p.add_argument("--format", default="mp4", choices=("mp4", "png"), dest="fmt")
    p.add_argument("--frames", default=None, help="frame selection START:STOP:STEP (python slice), or one index")
    p.add_argument("--cameras", default=None, help="comma-separated camera names (default: all in the episode)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output directory")


def _refine(p: argparse.ArgumentParser) -> None:
    p.add_argument("source", help="directory of raw HDF5 episodes, one episode file, or a LeRobot dataset")
    p.add_argument("--recipe", default=None, help="build recipe: the robot (URDF, joint map) and its cameras "
                   "(required for raw episodes; a dataset built by imac carries its own)")
    p.add_argument("--calibration", default=None,
                   help="calibration JSON to refine (never modified; default: the recipe's cameras.calibration, "
                        "or the dataset's)")
    p.add_argument("--out", required=True, help="refined calibration JSON to write")
    p.add_argument("--robot-pixels", default="auto",
                   help="where the robot's pixels come from: auto (default: sim if recorded, else edges), sim, "
                        "edges, or a mask directory DIR/<episode>/<camera>/<frame:06d>.png (<episode>: the "
                        "episode file's stem, or episode_000000... for a dataset)")
    p.add_argument("--cameras", default=None, help="comma-separated cameras (default: every calibrated one)")
    p.add_argument("--frames", type=int, default=8, help="frames per camera (default 8)")
    p.add_argument("--min-separation", type=float, default=0.1,
                   help="smallest distance between chosen frames' joint vectors, in radians after the "
                        "recipe's joint map (default 0.1)")
    p.add_argument("--method", default=None, help="gradient (default), nelder-mead or powell")
    p.add_argument("--refine-focal", action="store_true", help="also refine the focal length")
    p.add_argument("--near", type=float, default=0.0,
                   help="renderer near clip plane in metres (default 0; simulated episodes: the simulator's)")
    p.add_argument("--report", default=None, help="report directory (default: <out>.report beside --out)")
    p.add_argument("--overwrite", action="store_true", help="replace existing outputs (never inputs)")


def _name_value(text: str) -> tuple[str, str]:
    name, sep, value = text.partition("=")
    if not sep or not name or not value:
        raise argparse.ArgumentTypeError(f"expected CAMERA=VALUE, got {text!r}")
    return name, value


def _fov(text: str) -> tuple[str, float]:
    name, sep, value = text.rpartition("=")
    try:
        return (name if sep else "*"), float(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected DEG or CAMERA=DEG, got {text!r}") from None


def _calibrate(p: argparse.ArgumentParser) -> None:
    p.add_argument("source", help="directory of raw HDF5 episodes, one episode file, or a LeRobot dataset")
    p.add_argument("--recipe", required=True, help="build recipe: the robot (URDF, joint map)")
    p.add_argument("--out", required=True, help="calibration JSON to write (the cameras found)")
    p.add_argument("--mount", type=_name_value, action="append", default=[], metavar="CAMERA=LINK",
                   help="a wrist camera and the URDF link it is mounted on (repeatable)")
    p.add_argument("--fov", type=_fov, action="append", default=[], metavar="[CAMERA=]DEG",
                   help="nominal vertical field of view in degrees, for every camera or one (repeatable); the "
                        "focal length is then estimated (none: 25, 50 and 90 degrees are tried)")
    p.add_argument("--intrinsics", default=None, help="calibration JSON whose K are the recorded intrinsics (used as is)")
    p.add_argument("--depth", default="recorded", choices=("recorded", "da3"),
                   help="recorded depth (default) or Depth Anything 3's monocular model, scale estimated")
    p.add_argument("--estimate-depth-scale", action="store_true",
                   help="do not trust the recorded depth's scale: estimate it with the pose (always so with da3)")
    p.add_argument("--da3-model", default=None, help="local Depth Anything 3 metric weights directory (--depth da3)")
    p.add_argument("--cameras", default=None, help="comma-separated cameras (default: every camera of the source)")
    p.add_argument("--frames", type=int, default=10, help="frames registered together per camera (default 10)")
    p.add_argument("--candidates", type=int, default=60, help="frames read, spread over the episodes (default 60)")
    p.add_argument("--refine", default="edges", choices=("edges", "none"),
                   help="hand the result to `qa refine` with the edge cue (default), or not")
    p.add_argument("--near", type=float, default=0.0, help="renderer near clip for the refinement (simulated: 0.166)")
    p.add_argument("--max-time-offset", type=float, default=200.0, metavar="MS",
                   help="search each camera's time offset to the joint states within +- MS milliseconds "
                        "(default 200; 0: cameras in step, not searched)")
    p.add_argument("--report", default=None, help="report directory (default: <out>.report beside --out)")
    p.add_argument("--overwrite", action="store_true", help="replace existing outputs (never inputs)")
    p.add_argument("--no-progress", action="store_true")


def _preview(p: argparse.ArgumentParser) -> None:
    p.add_argument("root", help="the built dataset's root directory")
    p.add_argument("--episode", type=int, default=0, help="episode index (default 0)")
    p.add_argument("--out", default=None, help="output mp4 (default ./ROOTNAME_episode_N.mp4)")
    p.add_argument("--depth-max", type=float, default=2.0, help="far end of the depth colour map, metres")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output file")
    p.add_argument("--no-progress", action="store_true")


def _simulate(p: argparse.ArgumentParser) -> None:  # defaults: SimConfig's
    p.add_argument("--task", help=f"one of {TASKS} (default transfer_cube)")
    p.add_argument("--episodes", type=int, help="number of episodes (default 2)")
    p.add_argument("--out", required=True, type=Path, help="output directory")
    p.add_argument("--width", type=int, help="image width (default 320)")
    p.add_argument("--height", type=int, help="image height (default 240)")
    p.add_argument("--seed", type=int, help="episode i uses seed + i (default 0)")
    p.add_argument("--noise", type=float, help="policy noise in [0, 1] (default 0 = exact)")
    p.add_argument("--frame-stride", type=int, help="record every n-th 50 Hz control step (default 2 = 25 fps)")
    p.add_argument("--max-steps", type=int, help="cap on 50 Hz control steps per episode")
    p.add_argument("--segmentation", action="store_true", help="also store geom-id segmentation")
    p.add_argument("--no-depth", action="store_true", help="do not render depth")
    p.add_argument("--compress", action="store_true", help="store RGB as JPEG (ALOHA compressed variant)")
    p.add_argument("--shadows", action="store_true", help="render gym-aloha's shadows (slow on the CPU)")
    p.add_argument("--antialias", action="store_true", help="4x multisampled RGB")
    p.add_argument("--overwrite", action="store_true", help="replace episodes already in --out")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def _joints(p: argparse.ArgumentParser) -> None:
    p.add_argument("urdf", type=Path)
    p.add_argument("--package-dir", type=_package_dir, action="append", default=[], metavar="NAME=PATH",
                   help="the directory that package://NAME/ stands for (repeatable)")
    p.add_argument("--lerobot-robot", choices=sorted(LEROBOT_ARMS),
                   help="print the joint map of this LeRobot robot type, its values in LeRobot's units")
    p.add_argument("--lerobot-units", choices=UNITS,
                   help="the body joints' units the dataset was recorded in (default: the robot type's: degrees for "
                        "the SO arms, range_m100_100 for the Koch)")
    p.add_argument("--lerobot-calibration", type=Path, metavar="FILE",
                   help="the arm's LeRobot calibration file (<id>.json): needed for range_m100_100")


def build_parser(prog: str = "imac") -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=prog, description="LeRobot datasets with action-derived control videos "
                                                            "(motion, depth, contact). docs/ has the details.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    _build(sub.add_parser("build", help="build a dataset with every added stream from a recipe"))
    _augment(sub.add_parser("augment", help="add the streams to an existing LeRobot dataset"))
    _validate(sub.add_parser("validate", help="check a built dataset (exit 2 with a report when it is not valid)"))
    qa = sub.add_parser("qa", help="calibration overlay, calibration from nothing and refinement, preview of a built episode")
    qa_sub = qa.add_subparsers(dest="qa_command", required=True, metavar="QA_COMMAND")
    _overlay(qa_sub.add_parser("overlay", help="draw the rendered robot's outline over an episode's frames"))
    _refine(qa_sub.add_parser("refine", help="refine camera poses by aligning the rendered robot with the "
                                             "robot's pixels (docs/calibration.md)"))
    _calibrate(qa_sub.add_parser("calibrate", help="find every camera's pose from depth and joint states, with no "
                                                   "starting calibration (docs/calibration.md)"))
    _preview(qa_sub.add_parser("preview", help="write an mp4 mosaic of every stream of a built episode"))
    _simulate(sub.add_parser("simulate", help="record scripted gym-aloha episodes as ALOHA HDF5"))
    robot = sub.add_parser("robot", help="inspect a URDF for a recipe's robot: block")
    robot_sub = robot.add_subparsers(dest="robot_command", required=True, metavar="ROBOT_COMMAND")
    _joints(robot_sub.add_parser("joints", help="list movable joints, limits, mimic relations and visual links, "
                                                "and print a recipe robot: block to start from"))
    return parser


def command_of(args: argparse.Namespace) -> str:
    sub = getattr(args, "qa_command", None) or getattr(args, "robot_command", None)
    return f"{args.command} {sub}" if sub else args.command
