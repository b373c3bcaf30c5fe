"""The SO-101 round trip in simulation (issue 64): record, calibrate from nothing, build, compare.

1. ``benchmarks/so101_sim.py`` records the arm in MuJoCo from two fixed cameras of known placement, its joint
   states in LeRobot's own units: the body in degrees, and in -100..100 through a LeRobot calibration file made
   for it (the gripper 0..100 in both); HDF5 episodes with depth, LeRobot datasets without depth, and (LeRobot 0.6
   and later) LeRobot datasets with LeRobot's own depth maps, each by LeRobot's own writer.
2. ``imac qa calibrate`` finds both cameras from depth and joint states alone, per leg and convention; nominal
   fields of view 15 % off the truth, no refinement, no time-offset search (the cameras are in step).
3. ``python -m imac_data.build`` builds each with the calibration found, and the built dataset's robot masks (its
   rig, read back from the dataset alone, at its recorded states: what its motion images draw) are compared with
   MuJoCo's segmentation of the arm. The blind baseline is a camera placed by hand: the truth 2 cm and 2 degrees
   off, at the nominal field of view.

The legs (``--legs``), each in both conventions:

* ``hdf5``: the HDF5 episodes, calibrated from their recorded depth and built, with ``recipes/so101_lerobot.yaml``'s
  robot (degrees: the platform as shipped) or, for -100..100, the ``robot:`` block that ``imac robot joints
  --lerobot-robot so101_follower --lerobot-units range_m100_100 --lerobot-calibration FILE`` prints;
* ``lerobot``: the LeRobot dataset without depth, through ``recipes/so101_lerobot.yaml`` itself (source type
  ``lerobot``; ``depth: none``; for -100..100 the platform with ``units: range_m100_100`` and the calibration
  file): a dataset without depth cannot place its cameras, so ``qa calibrate`` reads the same recording's HDF5
  depth; the build reads the LeRobot dataset alone;
* ``lerobot_depth`` (LeRobot 0.6 and later, the Python 3.12 line): the LeRobot dataset with LeRobot's depth maps,
  through the same recipe with its shipped ``depth:`` section (``observation.images.{cam}_depth``): ``qa
  calibrate`` finds the cameras from the dataset's own depth, and the build reads it alone.

``python -m benchmarks.so101_round_trip [--legs hdf5,lerobot] [--height 480 --width 640 --episodes 2 --frames 120
--work DIR]`` prints the table (leg, convention, camera, position error mm, angle error deg, IoU, the baseline's
IoU). The default legs are every leg the installed LeRobot can write.
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import yaml

from benchmarks import so101_sim
from imac_data import lerobot_compat as lr
from imac_data.cli import main as imac_main
from imac_data.core.cameras import Camera, intrinsics_from_fovy, load_calibration
from imac_data.core.render import make_renderer
from imac_data.core.rig import Rig
from imac_data.core.robot import so101
from imac_data.core.robot.lerobot_units import joint_map, read_calibration
from imac_data.recipes import load_recipe

ROOT = Path(__file__).resolve().parent.parent
RECIPE = ROOT / "recipes" / "so101_lerobot.yaml"
NOMINAL = {"front": 1.15, "side": 0.85}  # nominal field of view / truth
LEGS = ("hdf5", "lerobot", "lerobot_depth")


def fovy(cam: Camera) -> float:
    """A camera's vertical field of view in degrees."""
    return float(np.degrees(2 * np.arctan(cam.height / 2 / cam.K[1, 1])))


def write_recipes(work: Path, paths: dict, hw: tuple[int, int]) -> dict[str, Path]:
    """Per convention, a copy of ``recipes/so101_lerobot.yaml`` reading the HDF5 episodes (their recorded depth) and
    the calibration ``qa calibrate`` writes (``<work>/<convention>.calibration.json``); the -100..100 copy's
    ``robot:`` block is the one ``imac robot joints`` prints for the calibration file."""

    base = yaml.safe_load(RECIPE.read_text())
    out = {}
    for units in so101_sim.CONVENTIONS:
        r = dict(base, name=f"so101_round_trip_{units}", fps=so101_sim.FPS)
        r["cameras"] = {"calibration": str(work / f"{units}.calibration.json")}
        r["source"] = {"type": "aloha_hdf5", "path": str(paths["hdf5"][units]), "episode_defaults": {"source": "teleop"}}
        r["augment"] = dict(base["augment"], height=hw[0], width=hw[1])
        r["depth"] = {"source": "recorded"}
        if units != "degrees":
            limits = {"gripper": (-0.17453, 1.74533)}  # only the gripper's range enters the map
            entries = joint_map("so101_follower", {**{m: (0, 0) for m in so101.ARM.body}, **limits}, units=units,
                                calibration=read_calibration(paths["calibration"]))
            r["robot"] = {"urdf": str(so101.urdf_path()), "joint_map": entries,
                          "gripper_links": list(so101.GRIPPER_LINKS)}
        out[units] = work / f"{units}.yaml"
        out[units].write_text(yaml.safe_dump(r, sort_keys=False))
    return out


def lerobot_recipe(work: Path, paths: dict, units: str, hw: tuple[int, int], *, depth: bool) -> Path:
    """``recipes/so101_lerobot.yaml`` as a user fills it in for the convention's LeRobot dataset: the dataset
    without depth (``depth: none``) or, with ``depth``, the one with LeRobot's depth maps (the shipped ``depth:``
    section); the calibration at ``<work>/<leg>_<units>.calibration.json``; for -100..100 the platform with its
    ``units`` and LeRobot's calibration file."""
    leg = "lerobot_depth" if depth else "lerobot"
    r = yaml.safe_load(RECIPE.read_text())
    r.update(name=f"so101_round_trip_{leg}_{units}", fps=so101_sim.FPS)
    r["cameras"] = {"calibration": str(work / f"{leg}_{units}.calibration.json")}
    r["source"]["path"] = str(paths[leg][units])
    r["augment"].update(height=hw[0], width=hw[1])
    if not depth:
        r["depth"] = {"source": "none"}
    if units != "degrees":
        r["robot"] = {"platform": "so101", "units": units, "calibration": str(paths["calibration"])}
    out = work / f"{leg}_{units}.yaml"
    out.write_text(yaml.safe_dump(r, sort_keys=False))
    return out


def calibrate(source: Path, recipe: Path, out: Path, truth: dict[str, Camera]) -> dict:
    """``imac qa calibrate`` (in this process), nominal fields of view; returns its report."""

    fov = [a for c, cam in truth.items() for a in ("--fov", f"{c}={NOMINAL[c] * fovy(cam):.2f}")]
    rc = imac_main(["qa", "calibrate", str(source), "--recipe", str(recipe), "--out", str(out), *fov, "--refine", "none",
               "--max-time-offset", "0", "--no-progress", "--overwrite"])
    if rc != 0:
        raise RuntimeError(f"qa calibrate exited {rc}")
    report = json.loads((out.with_name(out.stem + ".report") / "report.json").read_text())
    if report.get("refused"):
        raise RuntimeError(f"qa calibrate on {source} refused camera(s) {report['refused']} (its log above says why)")
    return report


def pose_error(a: Camera, b: Camera) -> tuple[float, float]:
    """Position error in mm and rotation angle in degrees between two fixed cameras."""
    R = a.T_world_cam[:3, :3].T @ b.T_world_cam[:3, :3]
    angle = np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1)))
    return float(1000 * np.linalg.norm(a.T_world_cam[:3, 3] - b.T_world_cam[:3, 3])), float(angle)


def pose_errors(calibration: Path, truth: dict[str, Camera]) -> dict[str, tuple[float, float]]:
    """Per camera of ``truth``, :func:`pose_error` of the one the calibration file ``calibration`` holds."""
    found = load_calibration(calibration)
    return {c: pose_error(found[c], truth[c]) for c in truth}


def build(recipe: Path, root: Path, repo: str) -> float:
    """``python -m imac_data.build`` as a user runs it; returns its wall time."""
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "imac_data.build", "--repo", repo, "--recipe", str(recipe), "--root",
                    str(root), "--overwrite", "--workers", "1", "--no-progress"], check=True, cwd=ROOT)
    return time.perf_counter() - t0


def built_states(root: Path) -> list[np.ndarray]:
    """The built dataset's ``observation.state`` per episode."""
    import pandas as pd

    df = pd.concat([pd.read_parquet(p) for p in sorted((root / "data").rglob("*.parquet"))])
    return [np.stack(g.sort_values("frame_index")["observation.state"].to_numpy())
            for _, g in df.groupby("episode_index")]


def iou(robot, cameras: dict[str, Camera], states: list[np.ndarray], masks: dict[str, np.ndarray],
        chunk: int = 16) -> dict[str, float]:
    """Per camera, the IoU over every frame of the robot rendered at ``states`` into ``cameras`` (their own size)
    with MuJoCo's arm ``masks`` (``episode_E/camera``)."""
    import torch


    renderer = make_renderer(robot)
    inter = {c: 0 for c in cameras}
    union = {c: 0 for c in cameras}
    for e, q in enumerate(states):
        for lo in range(0, len(q), chunk):
            views = renderer.render(torch.as_tensor(q[lo:lo + chunk], dtype=torch.float32), cameras)
            for c, v in views.items():
                ours, theirs = v.mask.numpy().astype(bool), masks[f"episode_{e}/{c}"][lo:lo + chunk]
                inter[c] += int((ours & theirs).sum())
                union[c] += int((ours | theirs).sum())
    return {c: inter[c] / max(union[c], 1) for c in cameras}


def built_iou(root: Path, cameras, masks: dict[str, np.ndarray]) -> tuple[list[np.ndarray], dict[str, float]]:
    """A built dataset's states per episode, and :func:`iou` of its own robot and ``cameras`` at those states."""
    rig = Rig.from_dataset(root)
    states = built_states(root)
    return states, iou(rig.robot, {c: rig.cameras[c] for c in cameras}, states, masks)


def hand_placed(truth: dict[str, Camera], seed: int = 0) -> dict[str, Camera]:
    """The blind baseline: each camera 2 cm and 2 degrees off the truth (random directions), at its nominal field
    of view."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    out = {}
    for c, cam in truth.items():
        axis, shift = rng.normal(size=3), rng.normal(size=3)
        T = cam.T_world_cam.copy()
        T[:3, :3] = T[:3, :3] @ Rotation.from_rotvec(np.radians(2.0) * axis / np.linalg.norm(axis)).as_matrix()
        T[:3, 3] += 0.02 * shift / np.linalg.norm(shift)
        K = intrinsics_from_fovy(NOMINAL[c] * fovy(cam), cam.width, cam.height)
        out[c] = Camera(c, K, cam.width, cam.height, T_world_cam=T)
    return out


def default_legs() -> tuple[str, ...]:
    """Every leg the installed LeRobot can write: ``lerobot_depth`` needs its depth maps (0.6 and later)."""
    try:
        so101_sim.check_depth_maps()
    except RuntimeError:
        return LEGS[:2]
    return LEGS


def round_trip(work: Path, *, height: int, width: int, episodes: int, frames: int, legs=("hdf5",),
               log=print) -> list[dict]:
    """The whole round trip in ``work``; one row per leg, convention and camera."""

    unknown = [leg for leg in legs if leg not in LEGS]
    if unknown:
        raise ValueError(f"legs {unknown}: not among {LEGS}")
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    paths = so101_sim.record(work / "recorded", episodes=episodes, frames=frames, height=height, width=width,
                             lerobot="lerobot" in legs, depth_maps="lerobot_depth" in legs)
    log(f"recorded {episodes} x {frames} frames at {height}x{width} in {time.perf_counter() - t0:.0f} s")
    truth = load_calibration(paths["truth"])
    masks = so101_sim.masks_of(paths["masks"])
    runs = []  # (leg, units, recipe, the source qa calibrate reads)
    if "hdf5" in legs:
        runs += [("hdf5", u, r, paths["hdf5"][u]) for u, r in write_recipes(work, paths, (height, width)).items()]
    for leg in (leg for leg in legs if leg != "hdf5"):
        depth = leg == "lerobot_depth"  # else the LeRobot dataset has none: the same recording's HDF5 depth
        runs += [(leg, u, lerobot_recipe(work, paths, u, (height, width), depth=depth),
                  paths["lerobot_depth"][u] if depth else paths["hdf5"][u]) for u in so101_sim.CONVENTIONS]
    rows = []
    for leg, units, recipe, source in runs:
        name = units if leg == "hdf5" else f"{leg}_{units}"
        calib = work / f"{name}.calibration.json"
        t0 = time.perf_counter()
        report = calibrate(source, recipe, calib, truth)
        t_cal = time.perf_counter() - t0
        root, repo = work / f"built_{name}", f"local/so101_round_trip_{name}"
        t_build = build(recipe, root, repo)
        states, built = built_iou(root, truth, masks)
        robot = Rig.robot_from_recipe(load_recipe(recipe))
        exact = iou(robot, truth, states, masks)
        blind = iou(robot, hand_placed(truth), states, masks)
        found = load_calibration(calib)
        for c in truth:
            mm, deg = pose_error(found[c], truth[c])
            rows.append({"leg": leg, "convention": units, "camera": c, "position_mm": mm, "angle_deg": deg,
                         "focal_pct": 100 * (found[c].K[0, 0] / truth[c].K[0, 0] - 1), "iou": built[c],
                         "iou_truth": exact[c], "iou_blind": blind[c], "calibrate_s": t_cal, "build_s": t_build,
                         "inliers": report["cameras"][c].get("inlier_ratio") if "cameras" in report else None,
                         "calibrated_from": str(Path(source).relative_to(work)), "lerobot": lr.version(),
                         "python": platform.python_version()})
    return rows


def format_table(rows: list[dict]) -> str:
    lines = ["| leg | convention | camera | position error mm | angle error deg | focal % | IoU (built) "
             "| IoU (true camera) | IoU (hand-placed, blind) |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r.get('leg', 'hdf5')} | {r['convention']} | {r['camera']} | {r['position_mm']:.2f} | "
                     f"{r['angle_deg']:.3f} | "
                     f"{r['focal_pct']:+.2f} | {r['iou']:.4f} | {r['iou_truth']:.4f} | {r['iou_blind']:.4f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> list[dict]:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--episodes", type=int, default=2)
    p.add_argument("--frames", type=int, default=120)
    p.add_argument("--work", type=Path, default=Path.home() / ".cache" / "imac" / "bench" / "so101_round_trip")
    p.add_argument("--legs", default=None,
                   help=f"comma-separated, of {','.join(LEGS)} (default: every leg this LeRobot can write)")
    p.add_argument("--json", type=Path, default=None, help="also write the rows here")
    args = p.parse_args(argv)
    legs = tuple(args.legs.split(",")) if args.legs else default_legs()
    rows = round_trip(args.work, height=args.height, width=args.width, episodes=args.episodes, frames=args.frames,
                      legs=legs)
    print(format_table(rows))
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return rows


if __name__ == "__main__":
    main()
