"""The whole build with each CPU renderer (the recipe's ``augment.renderer``): the same recorded episodes, the
same revision, built by the CLI in a fresh process with ``open3d`` (ray casting) and ``opengl`` (EGL
rasterisation) in turn, the order alternating every round.

    python -m benchmarks.renderer_build [--sizes 240x320 480x640] [--workers 2] [--rounds 2] [--episodes 4]

Per build: frames/s (the build's own seconds), CPU ms a frame of the process tree, and the render stage's CPU ms
a frame from the build's own stage table (``--timings``). Writes ``renderer_build.json`` into ``--out``
(default ``benchmarks/results/``). Run it on an idle machine: it is a timing."""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

from benchmarks.run_report import tag
from benchmarks.same_host import _BUILT, REPO, parse_size
from benchmarks.workload import RESULTS, Workload, commit, load_avg, log, machine, record, write_recipe

RENDERERS = ("open3d", "opengl")


def build(recipe: Path, source: Path, episodes: int, workers: int, root: Path) -> dict:
    """One ``python -m imac_data.build``, timed: the CLI's process tree and the build's own stage table."""
    timings = root.parent / f"{root.name}_timings.json"
    cmd = [sys.executable, "-m", "imac_data.build", "--repo", "local/renderer_build", "--recipe", str(recipe),
           "--source", str(source), "--episodes", str(episodes), "--root", str(root), "--overwrite", "--no-progress",
           "--workers", str(workers), "--timings", str(timings)]
    load_start = load_avg()
    t = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    output = proc.stdout.read()
    _, status, usage = os.wait4(proc.pid, 0)  # covers the CLI and the workers it reaped
    wall = time.perf_counter() - t
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode:
        raise RuntimeError(f"build failed (exit {proc.returncode}):\n{output[-3000:]}")
    frames = int(json.loads((root / "meta" / "info.json").read_text())["total_frames"])
    found = _BUILT.findall(output)
    stages = json.loads(timings.read_text())
    render_cpu = stages["stages"]["cpu_s"].get("render", 0.0)
    return {"cli_wall_s": wall, "build_s": float(found[-1][2]) if found else None, "frames": frames,
            "cpu_ms_per_frame": 1e3 * (usage.ru_utime + usage.ru_stime) / frames,
            "render_cpu_ms_per_frame": 1e3 * render_cpu / frames, "peak_rss_mb": usage.ru_maxrss / 1024,
            "load_avg_start": load_start}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.renderer_build", description=__doc__.split("\n\n")[0])
    p.add_argument("--sizes", nargs="+", type=parse_size, default=[(240, 320), (480, 640)], help="HxW")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--rounds", type=int, default=2)
    p.add_argument("--episodes", type=int, default=4)
    p.add_argument("--max-steps", type=int, help="50 Hz steps per episode (default: the whole script)")
    p.add_argument("--out", type=Path, default=RESULTS)
    args = p.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory(prefix="renderer_build_") as tmp:
        tmp = Path(tmp)
        for size in args.sizes:
            work = Workload(sizes=(size,), episodes=args.episodes, max_steps=args.max_steps)
            source = tmp / f"src_{tag(size)}"
            log(f"record {args.episodes} episodes at {tag(size)}")
            record(work, size, source)
            base = write_recipe(tmp / f"recipe_{tag(size)}.yaml", size, args.episodes, work.seed, work.noise)
            recipes = {}
            for name in RENDERERS:
                data = yaml.safe_load(base.read_text())
                data["augment"]["renderer"] = name
                recipes[name] = tmp / f"recipe_{tag(size)}_{name}.yaml"
                recipes[name].write_text(yaml.safe_dump(data, sort_keys=False))
            for r in range(args.rounds):
                for name in RENDERERS if r % 2 == 0 else RENDERERS[::-1]:
                    res = build(recipes[name], source, args.episodes, args.workers, tmp / f"out_{name}")
                    res.update(size=tag(size), renderer=name, round=r, workers=args.workers)
                    res["fps"] = res["frames"] / (res["build_s"] or res["cli_wall_s"])
                    log(f"{tag(size)} round {r} {name:7s}: {res['fps']:.2f} frames/s, {res['cpu_ms_per_frame']:.0f} "
                        f"CPU ms/frame (render {res['render_cpu_ms_per_frame']:.0f}), load {res['load_avg_start'][0]:.2f}")
                    rows.append(res)
    summary = {}
    for size in dict.fromkeys(r["size"] for r in rows):
        med = {name: {k: statistics.median(r[k] for r in rows if (r["size"], r["renderer"]) == (size, name))
                      for k in ("fps", "cpu_ms_per_frame", "render_cpu_ms_per_frame")} for name in RENDERERS}
        summary[size] = {**med, "cpu_ratio": med["opengl"]["cpu_ms_per_frame"] / med["open3d"]["cpu_ms_per_frame"],
                         "fps_ratio": med["opengl"]["fps"] / med["open3d"]["fps"]}
        log(f"{size}: opengl / open3d frames/s x{summary[size]['fps_ratio']:.2f}, CPU a frame "
            f"x{summary[size]['cpu_ratio']:.2f} (render {med['opengl']['render_cpu_ms_per_frame']:.0f} against "
            f"{med['open3d']['render_cpu_ms_per_frame']:.0f} CPU ms a frame)")
    result = {"commit": commit()[0], "machine": machine(), "args": {**vars(args), "out": str(args.out),
              "sizes": [tag(s) for s in args.sizes]}, "builds": rows, "summary": summary}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "renderer_build.json").write_text(json.dumps(result, indent=1, default=float) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
