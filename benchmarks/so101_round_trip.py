"""The SO-101 round trip in simulation (issue 64): record, calibrate from nothing, build, compare.

1. ``benchmarks/so101_sim.py`` records the arm in MuJoCo from two fixed cameras of known placement, its joint
   states in LeRobot's own units: the body in degrees, and in -100..100 through a LeRobot calibration file made
   for it (the gripper 0..100 in both); HDF5 episodes with depth, and LeRobot datasets without depth.
2. ``imac qa calibrate`` finds both cameras from depth and joint states alone, per convention, with the recipe
   ``recipes/so101_lerobot.yaml`` (degrees: the platform as shipped) or its copy whose ``robot:`` block is what
   ``imac robot joints --lerobot-robot so101_follower --lerobot-units range_m100_100 --lerobot-calibration FILE``
   prints; nominal fields of view 15 % off the truth, no refinement, no time-offset search (the cameras are in
   step).
3. ``python -m imac_data.build`` builds each convention's episodes with the calibration found, and the built
   dataset's robot masks (its rig, read back from the dataset alone, at its recorded states: what its motion
   images draw) are compared with MuJoCo's segmentation of the arm. The blind baseline is a camera placed by hand:
   the truth 2 cm and 2 degrees off, at the nominal field of view.

``python -m benchmarks.so101_round_trip [--height 480 --width 640 --episodes 2 --frames 120 --work DIR]`` prints
the table (convention, camera, position error mm, angle error deg, IoU, the baseline's IoU).
"""

from __future__ import annotations

import argparse
import json
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


def calibrate(source: Path, recipe: Path, out: Path, truth: dict[str, Camera]) -> dict:
    """``imac qa calibrate`` (in this process), nominal fields of view; returns its report."""

    fov = [a for c, cam in truth.items() for a in ("--fov", f"{c}={NOMINAL[c] * fovy(cam):.2f}")]
    rc = imac_main(["qa", "calibrate", str(source), "--recipe", str(recipe), "--out", str(out), *fov, "--refine", "none",
               "--max-time-offset", "0", "--no-progress", "--overwrite"])
    if rc != 0:
        raise RuntimeError(f"qa calibrate exited {rc}")
    return json.loads((out.with_name(out.stem + ".report") / "report.json").read_text())


def pose_error(a: Camera, b: Camera) -> tuple[float, float]:
    """Position error in mm and rotation angle in degrees between two fixed cameras."""
    R = a.T_world_cam[:3, :3].T @ b.T_world_cam[:3, :3]
    angle = np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1)))
    return float(1000 * np.linalg.norm(a.T_world_cam[:3, 3] - b.T_world_cam[:3, 3])), float(angle)


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


def round_trip(work: Path, *, height: int, width: int, episodes: int, frames: int, lerobot: bool = True,
               log=print) -> list[dict]:
    """The whole round trip in ``work``; one row per convention and camera."""

    work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    paths = so101_sim.record(work / "recorded", episodes=episodes, frames=frames, height=height, width=width,
                             lerobot=lerobot)
    log(f"recorded {episodes} x {frames} frames at {height}x{width} in {time.perf_counter() - t0:.0f} s")
    truth = load_calibration(paths["truth"])
    masks = so101_sim.masks_of(paths["masks"])
    recipes = write_recipes(work, paths, (height, width))
    rows = []
    for units, recipe in recipes.items():
        t0 = time.perf_counter()
        report = calibrate(paths["hdf5"][units], recipe, work / f"{units}.calibration.json", truth)
        t_cal = time.perf_counter() - t0
        t_build = build(recipe, work / f"built_{units}", f"local/so101_round_trip_{units}")
        root = work / f"built_{units}"
        rig = Rig.from_info(lr.LeRobotDatasetMetadata(f"local/so101_round_trip_{units}", root=root))
        states = built_states(root)
        built = iou(rig.robot, {c: rig.cameras[c] for c in truth}, states, masks)
        robot = Rig.robot_from_recipe(load_recipe(recipe))
        exact = iou(robot, truth, states, masks)
        blind = iou(robot, hand_placed(truth), states, masks)
        found = load_calibration(work / f"{units}.calibration.json")
        for c in truth:
            mm, deg = pose_error(found[c], truth[c])
            rows.append({"convention": units, "camera": c, "position_mm": mm, "angle_deg": deg,
                         "focal_pct": 100 * (found[c].K[0, 0] / truth[c].K[0, 0] - 1), "iou": built[c],
                         "iou_truth": exact[c], "iou_blind": blind[c], "calibrate_s": t_cal, "build_s": t_build,
                         "inliers": report["cameras"][c].get("inlier_ratio") if "cameras" in report else None})
    return rows


def format_table(rows: list[dict]) -> str:
    lines = ["| convention | camera | position error mm | angle error deg | focal % | IoU (built) | IoU (true camera) "
             "| IoU (hand-placed, blind) |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['convention']} | {r['camera']} | {r['position_mm']:.2f} | {r['angle_deg']:.3f} | "
                     f"{r['focal_pct']:+.2f} | {r['iou']:.4f} | {r['iou_truth']:.4f} | {r['iou_blind']:.4f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> list[dict]:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--episodes", type=int, default=2)
    p.add_argument("--frames", type=int, default=120)
    p.add_argument("--work", type=Path, default=Path.home() / ".cache" / "imac" / "bench" / "so101_round_trip")
    p.add_argument("--no-lerobot", action="store_true", help="skip writing the LeRobot datasets")
    p.add_argument("--json", type=Path, default=None, help="also write the rows here")
    args = p.parse_args(argv)
    rows = round_trip(args.work, height=args.height, width=args.width, episodes=args.episodes, frames=args.frames,
                      lerobot=not args.no_lerobot)
    print(format_table(rows))
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return rows


if __name__ == "__main__":
    main()
