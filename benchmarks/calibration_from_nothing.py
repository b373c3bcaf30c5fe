"""Calibration from nothing (``qa calibrate``): every camera found with no extrinsics, against
the simulators' true cameras.

    python -m benchmarks.calibration_from_nothing [--quick] [--cases aloha,placements,panda,scaled,sensor]
        [--seeds 3] [--placements 12] [--panda 6] [--refine edges|none] [--json PATH]
    python -m benchmarks.calibration_from_nothing --table FILE

The inputs carry no truth: plain HDF5 episodes (joint states, RGB, depth in mm) written by
``benchmarks/calibration_scenes.py``, with no calibration and no segmentation; the image size
and a nominal field of view 15 % off the truth (alternately too wide and too narrow). Each case
runs ``imac_data.calibrate.from_nothing.calibrate_from_nothing`` (the command's function, end
to end, writing its files) and compares what it wrote with the simulator's cameras: the norm of
the translation error (mm) and the rotation angle (degrees) of ``T_world_cam`` (fixed) or
``T_link_cam`` (wrist), and the focal length's error.

* ``aloha``: gym-aloha's scripted transfer-cube episodes (two per seed), MuJoCo's sensor depth
  (uint16 mm), every camera; goals: head within 3 mm and 0.3 deg, wrists 5 mm and 0.5 deg.
* ``placements``: the same joint states seen by head cameras at random poses from a fixed seed
  (upper hemisphere in front of the rig, 1.0-2.0 m from its base, looking at the workspace,
  vertical field of view 45 deg), rendered by MuJoCo; goal: all but one within 3 mm and 0.3 deg,
  and that one refused.
* ``panda``: the Franka Panda URDF of the ``pybullet`` package, through a recipe only, moving
  between random waypoints over a floor, rendered by pybullet's TinyRenderer from random
  placements around it; the same goal.
* ``scaled``: the aloha head camera with its depth multiplied by 1.07 and Gaussian noise of 1 %
  of the range, ``--estimate-depth-scale``; goal: 5 mm, 0.5 deg, scale within 1 %.
* ``sensor``: the aloha episodes with a depth sensor's faults on every camera
  (``calibration_scenes.sensor_faults``: axial noise of 0.002 z^2 m, 6-pixel holes over about 5 % of
  each image, half the pixels at depth edges flying between the two sides); the aloha goals, or
  refused by name.

``--quick`` (what CI's tests do, smaller): 120x160, one seed, one placement per case.
Times are per camera (search), plus the refinement's when it runs; the machine is shared, so
the JSON records the load average beside them.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

from benchmarks.calibration_scenes import (
    ALOHA_FOVY,
    ALOHA_MOUNTS,
    ALOHA_NEAR,
    ALOHA_RECIPE,
    aloha_episodes,
    aloha_placements,
    degrade_depth,
    panda_episodes,
    panda_recipe,
    random_placements,
    sensor_depth,
)
from imac_data.calibrate.from_nothing import calibrate_from_nothing
from imac_data.calibrate.scratch import pose_distance
from imac_data.core.cameras import load_calibration

RESULTS = Path(__file__).resolve().parent / "results"
GOALS = {"head": (3.0, 0.3), "wrist": (5.0, 0.5), "scaled": (5.0, 0.5)}
FOV_OFF = 0.15


def nominal(fovy: float, sign: int) -> float:
    """A nominal vertical field of view ``FOV_OFF`` off the truth (``sign`` +1 wider, -1 narrower)."""
    return fovy * (1 + sign * FOV_OFF)


def compare(truth: dict, out: Path, summary: dict, case: str, run: str, goal_of) -> list[dict]:
    """One row per camera: error against the truth, confidence, time; refused cameras too."""
    found = load_calibration(out) if out.is_file() else {}
    rows = []
    for c, cam in truth.items():
        row = {"case": case, "run": run, "camera": c, "goal": goal_of(c)}
        if c in found:
            e = found[c]
            a, b = (cam.T_link_cam, e.T_link_cam) if cam.is_mounted else (cam.T_world_cam, e.T_world_cam)
            t_mm, r_deg = pose_distance(a, b)
            entry = summary["cameras"][c]
            row.update(status="calibrated", t_mm=t_mm, r_deg=r_deg,
                       focal_err_pct=100 * (e.rescaled(cam.width, cam.height).K[0, 0] / cam.K[0, 0] - 1),
                       depth_scale=entry["depth_scale"], inlier_ratio=entry["inlier_ratio"],
                       residual_mm=entry["residual_mm"], search_s=entry["wall_s"],
                       refine_accepted=entry.get("refine_accepted"),
                       refine_moved_mm=entry.get("refine_pose_change", {}).get("t_mm"),
                       outline_px_after_refine=entry.get("outline_px_after_refine"))
            row["within_goal"] = bool(t_mm <= row["goal"][0] and r_deg <= row["goal"][1])
        else:
            row.update(status="refused", reason=summary.get("refused", {}).get(c, "not written"))
        rows.append(row)
    return rows


def _run(src: Path, out_dir: Path, **kw) -> tuple[dict, Path]:
    out = out_dir / "calib.json"
    try:
        summary = calibrate_from_nothing(src, out, progress=False, overwrite=True,
                                         log=lambda m: print(m, flush=True) if "REFUSED" in m else None, **kw)
    except Exception as e:  # every camera refused: the rows say so
        if type(e).__name__ != "CalibrationRefused":
            raise
        summary = {"cameras": {}, "refused": {"*": str(e)}}
    return summary, out


def aloha_case(tmp: Path, seed: int, hw, refine: str, max_steps=None) -> tuple[list[dict], float]:
    src = tmp / f"aloha{seed}"
    truth = aloha_episodes(src, seed=100 * seed, height=hw[0], width=hw[1], max_steps=max_steps)
    sign = 1 if seed % 2 == 0 else -1
    fov = {c: nominal(f, sign) for c, f in ALOHA_FOVY.items()}
    t0 = time.perf_counter()
    summary, out = _run(src, tmp / f"aloha{seed}.out", recipe=ALOHA_RECIPE, mounts=ALOHA_MOUNTS, fov=fov,
                        refine=refine, near=ALOHA_NEAR)
    rows = compare(truth, out, summary, "aloha", f"seed {seed}, fov {'+' if sign > 0 else '-'}15%",
                   lambda c: GOALS["wrist" if c in ALOHA_MOUNTS else "head"])
    for r in rows:
        r["refine_s_all_cameras"] = summary.get("refine_wall_s")
    return rows, time.perf_counter() - t0


def placements_case(tmp: Path, n: int, hw, quick: bool) -> tuple[list[dict], float]:
    base = tmp / "aloha_motion"
    if not base.exists():
        aloha_episodes(base, seed=7, height=60, width=80, max_steps=None if not quick else 300)
    poses = random_placements(n, 2026, centre=(0.0, 0.5, 0.15), front=(0, -1, 0), base=(0.0, 0.5, 0.0))
    src = tmp / "placements"
    truth = aloha_placements(src, base, poses, fovy=45.0, height=hw[0], width=hw[1])
    t0 = time.perf_counter()
    summary, out = _run(src, tmp / "placements.out", recipe=ALOHA_RECIPE, fov={"*": nominal(45.0, 1)},
                        refine="none")
    return compare(truth, out, summary, "placements", "seed 2026, fov +15%", lambda c: GOALS["head"]), \
        time.perf_counter() - t0


def panda_case(tmp: Path, n: int, hw, quick: bool) -> tuple[list[dict], float]:
    poses = random_placements(n, 7, centre=(0.35, 0.0, 0.35), front=(1, 0, 0))
    root = tmp / "panda"
    truth = panda_episodes(root, poses, seed=3, height=hw[0], width=hw[1], frames=30 if quick else 60,
                           episodes=1 if quick else 2)
    recipe = panda_recipe(root)
    t0 = time.perf_counter()
    summary, out = _run(root / "episodes", tmp / "panda.out", recipe=recipe, fov={"*": nominal(60.0, -1)},
                        refine="none", candidates=30 if quick else 60)
    return compare(truth, out, summary, "panda", "seed 7, fov -15%", lambda c: GOALS["head"]), \
        time.perf_counter() - t0


def scaled_case(tmp: Path, hw, max_steps=None) -> tuple[list[dict], float]:
    src = tmp / "aloha_scaled_src"
    truth = aloha_episodes(src, seed=5, height=hw[0], width=hw[1], max_steps=max_steps)
    degrade_depth(src, tmp / "aloha_scaled", "cam_high", scale=1.07, noise=0.01, seed=0)
    t0 = time.perf_counter()
    summary, out = _run(tmp / "aloha_scaled", tmp / "scaled.out", recipe=ALOHA_RECIPE, cameras=["cam_high"],
                        fov={"cam_high": nominal(78.0, 1)}, estimate_depth_scale=True, refine="none")
    rows = compare({"cam_high": truth["cam_high"]}, out, summary, "scaled", "x1.07, noise 1%, fov +15%",
                   lambda c: GOALS["scaled"])
    for r in rows:
        if r["status"] == "calibrated":
            r["scale_err_pct"] = 100 * (r["depth_scale"] * 1.07 - 1)  # the estimate undoes the 1.07
            r["within_goal"] = r["within_goal"] and abs(r["scale_err_pct"]) <= 1.0
    return rows, time.perf_counter() - t0


def sensor_case(tmp: Path, hw, max_steps=None) -> tuple[list[dict], float]:
    src = tmp / "aloha_sensor_src"
    truth = aloha_episodes(src, seed=11, height=hw[0], width=hw[1], max_steps=max_steps)
    sensor_depth(src, tmp / "aloha_sensor", seed=0)
    t0 = time.perf_counter()
    summary, out = _run(tmp / "aloha_sensor", tmp / "sensor.out", recipe=ALOHA_RECIPE, mounts=ALOHA_MOUNTS,
                        fov={c: nominal(f, 1) for c, f in ALOHA_FOVY.items()}, refine="none", near=ALOHA_NEAR)
    return compare(truth, out, summary, "sensor", "seed 11, sensor faults, fov +15%",
                   lambda c: GOALS["wrist" if c in ALOHA_MOUNTS else "head"]), time.perf_counter() - t0


def run(cases, *, quick: bool, seeds: int, placements: int, panda: int, refine: str, partial: Path | None) -> dict:
    hw = (120, 160) if quick else (480, 640)
    load0 = os.getloadavg()
    import subprocess

    rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=Path(__file__).parent, capture_output=True,
                         text=True).stdout.strip()
    result = {"height": hw[0], "width": hw[1], "quick": quick, "commit": rev, "rows": [], "case_wall_s": {}}
    with tempfile.TemporaryDirectory(prefix="imac-calib-") as d:
        tmp = Path(d)
        for case in cases:
            if case == "aloha":
                for s in range(1 if quick else seeds):
                    rows, wall = aloha_case(tmp, s, hw, refine, max_steps=300 if quick else None)
                    result["rows"] += rows
                    result["case_wall_s"][f"aloha seed {s}"] = wall
            elif case == "placements":
                rows, wall = placements_case(tmp, 1 if quick else placements, hw, quick)
                result["rows"] += rows
                result["case_wall_s"]["placements"] = wall
            elif case == "panda":
                rows, wall = panda_case(tmp, 1 if quick else panda, hw, quick)
                result["rows"] += rows
                result["case_wall_s"]["panda"] = wall
            elif case in ("scaled", "sensor"):
                rows, wall = (scaled_case if case == "scaled" else sensor_case)(tmp, hw, max_steps=300 if quick else None)
                result["rows"] += rows
                result["case_wall_s"][case] = wall
            else:
                raise SystemExit(f"unknown case {case!r}")
            print(format_table(result), flush=True)
            if partial:
                partial.write_text(json.dumps(result, indent=2, default=float))
    result["load_avg"] = [list(load0), list(os.getloadavg())]
    return result


def format_table(result: dict) -> str:
    lines = [f"{'case':<11} {'run':<28} {'camera':<16} {'status':<10} {'t mm':>6} {'r deg':>6} {'focal %':>8} "
             f"{'scale':>7} {'inliers':>8} {'res mm':>7} {'s':>5}  goal"]
    for r in result["rows"]:
        if r["status"] == "calibrated":
            lines.append(f"{r['case']:<11} {r['run']:<28} {r['camera']:<16} {r['status']:<10} {r['t_mm']:>6.2f} "
                         f"{r['r_deg']:>6.3f} {r['focal_err_pct']:>8.2f} {r['depth_scale']:>7.4f} "
                         f"{100 * r['inlier_ratio']:>7.1f}% {r['residual_mm']:>7.2f} {r['search_s']:>5.0f}  "
                         f"{'met' if r['within_goal'] else 'MISSED'} ({r['goal'][0]:g} mm, {r['goal'][1]:g} deg)")
        else:
            lines.append(f"{r['case']:<11} {r['run']:<28} {r['camera']:<16} REFUSED: {r['reason'][:150]}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true", help="120x160, one seed, one placement per case")
    p.add_argument("--cases", default="aloha,placements,panda,scaled,sensor")
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument("--placements", type=int, default=12)
    p.add_argument("--panda", type=int, default=6)
    p.add_argument("--refine", default="edges", choices=("edges", "none"), help="for the aloha case")
    p.add_argument("--json", default=str(RESULTS / "calibration_from_nothing.json"))
    p.add_argument("--table", default=None, metavar="JSON", help="only print a saved run's table")
    args = p.parse_args(argv)
    if args.table:
        print(format_table(json.loads(Path(args.table).read_text())))
        return {}
    path = Path(args.json)
    path.parent.mkdir(parents=True, exist_ok=True)
    result = run([c for c in args.cases.split(",") if c], quick=args.quick, seeds=args.seeds,
                 placements=args.placements, panda=args.panda, refine=args.refine,
                 partial=path.with_suffix(".partial.json"))
    print(format_table(result))
    path.write_text(json.dumps(result, indent=2, default=float))
    path.with_suffix(".partial.json").unlink(missing_ok=True)
    print(f"wrote {path}")
    return result


if __name__ == "__main__":
    main()
