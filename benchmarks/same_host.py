"""Throughput of two revisions on the same machine, the same inputs, interleaved.

    python -m benchmarks.same_host [--baseline afa9031] [--sizes 240x320 480x640]
                                   [--workers 1 2] [--rounds 2] [--episodes 4] [--max-steps N]

Frames/s measured on one machine cannot be compared with frames/s measured on another,
and on a shared machine not even with those of another hour. This benchmark therefore
builds the *same* recorded episodes with the CLI of both revisions (``python -m
imac_data.build.hdf5``, each in a fresh process, the baseline from a ``git worktree``),
alternating the order every round, and reports the ratio per round beside the load
average. The default baseline, afa9031, is ``main`` as the streamed-pipeline issue measured
it (5.8 frames/s at 240x320 and 1.1 at 480x640 on its machine).

Per build: the CLI's wall seconds (imports included), the build's own seconds (the line it
prints), CPU seconds of the process tree (``wait4``), the peak RSS of the largest process,
and the frames built. Writes ``same_host.json`` and ``same_host.md`` into ``--out``
(default ``benchmarks/results/``). The episodes are recorded with this revision's simulator;
both revisions read the same files.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.run_report import ratio_lines, same_host_table, tag
from benchmarks.workload import RESULTS, Workload, commit, load_avg, log, machine, record, write_recipe

REPO = Path(__file__).resolve().parent.parent
BASELINE = "afa9031"  # main before the streamed pipeline: the 5.8 / 1.1 frames/s
_BUILT = re.compile(r"built \S+: (\d+) episodes, (\d+) frames in ([0-9.]+) s")


def parse_size(text: str) -> tuple[int, int]:
    h, w = text.lower().split("x")
    return int(h), int(w)


def checkout(rev: str, where: Path) -> Path:
    """A detached worktree of ``rev`` at ``where`` (removed again by :func:`drop_checkout`)."""
    subprocess.run(["git", "worktree", "add", "--detach", str(where), rev], cwd=REPO, check=True,
                   capture_output=True, text=True)
    return where


def drop_checkout(where: Path) -> None:
    subprocess.run(["git", "worktree", "remove", "--force", str(where)], cwd=REPO, capture_output=True, text=True)


def cli_build(tree: Path, recipe: Path, source: Path, episodes: int, workers: int, root: Path) -> dict:
    """One ``python -m imac_data.build`` of the revision checked out at ``tree``, timed."""
    env = {**os.environ, "PYTHONPATH": str(tree)}
    cmd = [sys.executable, "-m", "imac_data.build", "--repo", f"local/same_host_{source.name}", "--recipe",
           str(recipe), "--source", str(source), "--episodes", str(episodes), "--root", str(root), "--overwrite",
           "--no-progress", "--workers", str(workers)]
    load_start = load_avg()
    log_path = root.parent / f"{root.name}.log"
    t = time.perf_counter()
    with open(log_path, "w") as out:
        proc = subprocess.Popen(cmd, cwd=tree, env=env, stdout=out, stderr=subprocess.STDOUT)
        # wait4, not Popen.wait: its usage covers the CLI and the workers it reaped
        _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t
    proc.returncode = os.waitstatus_to_exitcode(status)  # reaped here: Popen must not wait for it again
    output = log_path.read_text(errors="replace")
    if proc.returncode:
        raise RuntimeError(f"{tree}: build failed (exit {proc.returncode}):\n{output[-3000:]}")
    found = _BUILT.findall(output)
    info = json.loads((root / "meta" / "info.json").read_text())
    shutil.rmtree(root, ignore_errors=True)
    return {"cli_wall_s": wall, "build_s": float(found[-1][2]) if found else None,
            "frames": int(info["total_frames"]), "load_avg_start": load_start, "load_avg_end": load_avg(),
            "cpu_s": usage.ru_utime + usage.ru_stime, "peak_rss_mb": usage.ru_maxrss / 1024}


def run(args, tmp: Path) -> dict:
    inputs = []
    for size in args.sizes:
        work = Workload(sizes=(size,), episodes=args.episodes, max_steps=args.max_steps)
        source = tmp / f"src_{tag(size)}"
        log(f"record {args.episodes} episodes at {tag(size)}")
        record(work, size, source)
        inputs.append((size, write_recipe(tmp / f"recipe_{tag(size)}.yaml", size, args.episodes, work.seed,
                                          work.noise), source, args.episodes))
    return {"date": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"), "machine": machine(),
            "commit": commit()[0], "episodes": args.episodes,
            **compare(args.baseline, inputs, args.workers, args.rounds, tmp)}


def compare(baseline: str, inputs, workers, rounds: int, tmp: Path) -> dict:
    """Build each ``(size, recipe, source, episodes)`` of ``inputs`` with both revisions' CLIs, for every worker
    count and round, the order alternating; the rows and :func:`summarise` of them."""
    trees = {"baseline": checkout(baseline, tmp / "baseline"), "this": REPO}
    rows = []
    try:
        for size, recipe, source, episodes in inputs:
            for r in range(rounds):
                for w in workers:
                    order = ["baseline", "this"] if (r + w) % 2 == 0 else ["this", "baseline"]
                    for name in order:
                        res = cli_build(trees[name], recipe, source, episodes, w, tmp / f"out_{name}")
                        res.update(size=tag(size), revision=name, workers=w, round=r)
                        res["fps"] = res["frames"] / (res["build_s"] or res["cli_wall_s"])
                        res["cpu_ms_per_frame"] = 1e3 * res["cpu_s"] / res["frames"]
                        log(f"{tag(size)} round {r} {name:8s} {w} worker(s): {res['fps']:.2f} frames/s, "
                            f"{res['cpu_ms_per_frame']:.0f} CPU ms/frame, load {res['load_avg_start'][0]:.2f}")
                        rows.append(res)
    finally:
        drop_checkout(trees["baseline"])
    return {"baseline": baseline, "rounds": rounds, "builds": rows, "summary": summarise(rows)}


def summarise(rows: list[dict]) -> dict:
    """Per size: each revision's best worker setting (median frames/s over rounds) and the
    ratios of the medians; per round and worker count: the ratio of that pair."""
    out = {}
    for size in dict.fromkeys(r["size"] for r in rows):
        at = [r for r in rows if r["size"] == size]
        med = {}
        for name, w in dict.fromkeys((r["revision"], r["workers"]) for r in at):
            runs = [r for r in at if (r["revision"], r["workers"]) == (name, w)]
            med[name, w] = {"fps": statistics.median(r["fps"] for r in runs),
                            "cpu_ms_per_frame": statistics.median(r["cpu_ms_per_frame"] for r in runs)}
        best = {name: max(((w, m) for (n, w), m in med.items() if n == name), key=lambda x: x[1]["fps"])
                for name in ("baseline", "this")}
        by = {(x["round"], x["workers"], x["revision"]): x for x in at}
        pairs = [{"round": r, "workers": w, "fps_ratio": this["fps"] / base["fps"],
                  "cpu_ratio": this["cpu_ms_per_frame"] / base["cpu_ms_per_frame"]}
                 for (r, w, name), this in by.items() if name == "this" and (base := by.get((r, w, "baseline")))]
        out[size] = {
            "per_setting": {f"{n} w{w}": m for (n, w), m in med.items()},
            "best": {n: {"workers": w, **m} for n, (w, m) in best.items()},
            "fps_ratio_best": best["this"][1]["fps"] / best["baseline"][1]["fps"],
            "cpu_ratio_best": best["this"][1]["cpu_ms_per_frame"] / best["baseline"][1]["cpu_ms_per_frame"],
            "pairs": sorted(pairs, key=lambda p: (p["round"], p["workers"])),
        }
    return out


def markdown(res: dict) -> str:
    lines = ["# Same machine, two revisions\n",
             f"`python -m benchmarks.same_host` on {res['date']}: `{res['commit'][:12]}` (this) vs `{res['baseline']}` "
             f"(baseline), {res['machine']}; {res['episodes']} scripted `transfer_cube` episodes per size, 3 views, "
             f"recorded depth, built by each revision's CLI in a fresh process, {res['rounds']} round(s), the order "
             "alternating.\n",
             *same_host_table(res["builds"]), ""]
    lines += ratio_lines(res["summary"])
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--baseline", default=BASELINE, help=f"the revision to compare with (default {BASELINE})")
    p.add_argument("--sizes", nargs="+", type=parse_size, default=[(240, 320), (480, 640)], help="HxW")
    p.add_argument("--workers", nargs="+", type=int, default=[1, 2])
    p.add_argument("--rounds", type=int, default=2)
    p.add_argument("--episodes", type=int, default=4)
    p.add_argument("--max-steps", type=int, help="50 Hz steps per episode (default: the whole script)")
    p.add_argument("--out", type=Path, default=RESULTS)
    p.add_argument("--keep", type=Path, help="work in this directory and keep it (default: a temporary one)")
    args = p.parse_args(argv)
    if args.keep:
        args.keep.mkdir(parents=True, exist_ok=True)
        res = run(args, args.keep)
    else:
        with tempfile.TemporaryDirectory(prefix="imac_same_host_") as d:
            res = run(args, Path(d))
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "same_host.json").write_text(json.dumps(res, indent=1))
    (args.out / "same_host.md").write_text(markdown(res))
    print(markdown(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
