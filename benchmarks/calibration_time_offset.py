"""Cameras out of step with the joint states (``qa calibrate``'s time offset), against the simulator's
true cameras and the true offset.

    python -m benchmarks.calibration_time_offset [--lags 1,2,4,6] [--height 480 --width 640]
        [--cameras cam_high,cam_left_wrist,cam_right_wrist] [--seed 0] [--max-steps N] [--json PATH]
    python -m benchmarks.calibration_time_offset --table FILE

The scene (``benchmarks/calibration_scenes.py``): gym-aloha's scripted transfer-cube episode recorded
at 50 fps, subsampled to 25 fps with every camera's RGB and depth taken ``lag`` 20 ms control steps
before the joint states (``--lags 1,2,4,6``: half a frame and 1, 2 and 3 frames at 25 fps), so the
cameras lag by 20-120 ms. The simulator's own frames lag by one physics step more (2 ms), which the
true offset includes. Each lag runs ``calibrate_from_nothing`` twice on the same episodes, with no
calibration, no segmentation and a nominal field of view 15 % too wide: with the time offset searched
(+-200 ms, the default) and blind (offset fixed at 0, as before the search existed). Per camera the
table gives the true and found offset, the offset's error, the pose error (norm of the translation
error, rotation angle of ``T_world_cam`` or ``T_link_cam``) and the blind run's pose error or refusal.
Goals: the offset within 5 ms; head 3 mm and 0.3 deg, wrists 5 mm and 0.5 deg.
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
    ALOHA_RECIPE,
    aloha_out_of_step,
    aloha_recorded_50fps,
)
from imac_data.calibrate.from_nothing import calibrate_from_nothing
from imac_data.calibrate.scratch import CalibrationRefused, pose_distance
from imac_data.core.cameras import load_calibration

RESULTS = Path(__file__).resolve().parent / "results"
GOALS = {"head": (3.0, 0.3), "wrist": (5.0, 0.5)}
OFFSET_GOAL_MS = 5.0


def _run(src: Path, out: Path, cams: list[str], window: float) -> tuple[dict, float]:
    t0 = time.perf_counter()
    try:
        summary = calibrate_from_nothing(src, out, recipe=ALOHA_RECIPE, cameras=cams,
                                         mounts={c: ALOHA_MOUNTS[c] for c in cams if c in ALOHA_MOUNTS},
                                         fov={c: ALOHA_FOVY[c] * 1.15 for c in cams}, refine="none",
                                         time_offset_window=window, progress=False)
    except CalibrationRefused as e:  # every camera refused: the command writes nothing
        text = str(e)
        summary = {"cameras": {}, "refused": {c: _own_reason(text, c) for c in cams}}
    return summary, time.perf_counter() - t0


def _own_reason(text: str, camera: str) -> str:
    """Camera ``camera``'s part of a refusal that lists every camera's ("...; camera 'x': ...")."""
    start = text.find(f"camera {camera!r}: ")
    if start < 0:
        return text
    end = text.find("; camera '", start + 1)
    return text[start:end if end > 0 else None]


def _errors(truth, out: Path, summary: dict) -> dict:
    found = load_calibration(out) if out.is_file() else {}
    rows = {}
    for c, cam in truth.items():
        if c not in found:
            rows[c] = {"refused": summary["refused"].get(c, "not written")}
            continue
        a, b = (cam.T_link_cam, found[c].T_link_cam) if cam.is_mounted else (cam.T_world_cam, found[c].T_world_cam)
        t_mm, r_deg = pose_distance(a, b)
        e = summary["cameras"][c]
        rows[c] = {"t_mm": t_mm, "r_deg": r_deg, "offset_ms": 1e3 * found[c].time_offset_s,
                   "rise": e.get("time_offset_rise"), "inliers": e["inlier_ratio"],
                   "inliers_at_zero": e.get("inlier_ratio_at_zero_offset"), "wall_s": e.get("wall_s")}
    return rows


def run(lags: list[int], cams: list[str], *, height: int, width: int, seed: int, max_steps: int | None,
        work: Path, log=print, after_lag=None) -> list[dict]:
    """Every lag's rows; ``after_lag(rows)`` is called with the rows so far after each lag."""
    raw = work / "raw50"
    log(f"recording seed {seed} at 50 fps, {width}x{height}")
    truth = aloha_recorded_50fps(raw, seed=seed, episodes=1, height=height, width=width, max_steps=max_steps)
    truth = {c: truth[c] for c in cams}
    rows = []
    for lag in lags:
        src = work / f"lag{lag}"
        true = aloha_out_of_step(raw, src, -lag)
        found, wall = _run(src, work / f"lag{lag}.json", cams, 0.2)
        blind, wall0 = _run(src, work / f"lag{lag}_blind.json", cams, 0.0)
        with_offset = _errors(truth, work / f"lag{lag}.json", found)
        without = _errors(truth, work / f"lag{lag}_blind.json", blind)
        for c in cams:
            kind = "wrist" if c in ALOHA_MOUNTS else "head"
            row = {"lag_steps": lag, "lag_frames": lag / 2, "camera": c, "kind": kind, "true_ms": 1e3 * true,
                   "goal": GOALS[kind], **with_offset[c], "run_wall_s": wall, "blind_run_wall_s": wall0,
                   "blind": without[c]}
            if "offset_ms" in row:
                row["offset_err_ms"] = row["offset_ms"] - row["true_ms"]
            rows.append(row)
            log(_line(row))
        if after_lag is not None:
            after_lag(rows)
    return rows


def _pose(e: dict) -> str:
    if "refused" in e:
        return "refused: " + e["refused"].split(": ", 1)[-1][:60]
    return f"{e['t_mm']:.2f} mm {e['r_deg']:.3f}°"


def _line(r: dict) -> str:
    if "refused" in r:
        found = f"{'refused':>9} {'':>8}"
    else:
        found = f"{r['offset_ms']:>+9.1f} {r['offset_err_ms']:>+8.1f}"
    ok = "refused" not in r and abs(r["offset_err_ms"]) <= OFFSET_GOAL_MS and r["t_mm"] <= r["goal"][0] \
        and r["r_deg"] <= r["goal"][1]
    return (f"{r['lag_frames']:>5.1f} {r['camera']:<16} {r['true_ms']:>+8.1f} {found} {_pose(r):>18} "
            f"{'yes' if ok else 'NO':>5}  {_pose(r['blind'])}")


def table(rows: list[dict]) -> str:
    head = (f"{'lag':>5} {'camera':<16} {'true ms':>8} {'found ms':>9} {'err ms':>8} {'pose error':>18} "
            f"{'goal':>5}  blind (offset 0)")
    return "\n".join([head] + [_line(r) for r in rows])


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--lags", default="1,2,4,6", help="camera lags in 20 ms control steps (2 = one frame at 25 fps)")
    p.add_argument("--cameras", default="cam_high,cam_left_wrist,cam_right_wrist")
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--max-steps", type=int, default=None, help="50 Hz control steps of the episode (default: all)")
    p.add_argument("--json", default=str(RESULTS / "calibration_time_offset.json"))
    p.add_argument("--table", default=None, metavar="JSON", help="only print a saved run's table")
    a = p.parse_args(argv)
    if a.table:
        saved = json.loads(Path(a.table).read_text())
        print(table(saved["rows"]))
        return saved
    t0 = time.perf_counter()
    lags = [int(x) for x in a.lags.split(",")]

    def save(rows: list[dict]) -> dict:
        # after every lag, so that a long grid cut short keeps the lags it finished
        done = sorted({r["lag_steps"] for r in rows})
        result = {"args": vars(a), "rows": rows, "lags_done": done, "complete": len(done) == len(lags),
                  "wall_s": time.perf_counter() - t0, "load_avg": list(os.getloadavg())}
        if a.json:
            Path(a.json).parent.mkdir(parents=True, exist_ok=True)
            Path(a.json).write_text(json.dumps(result, indent=1, default=float))
        return result

    with tempfile.TemporaryDirectory(prefix="calib_offset_") as tmp:
        rows = run(lags, a.cameras.split(","), height=a.height, width=a.width, seed=a.seed, max_steps=a.max_steps,
                   work=Path(tmp), after_lag=save)
    print(table(rows))
    return save(rows)


if __name__ == "__main__":
    main()
