"""Where the test suite's time goes: per file, per test, and per Python process it starts.

    python -m benchmarks.suite_profile [--json FILE] [-- PYTEST ARGS...]

Runs the README's test command (``pytest -q -n 2 --dist loadfile``, or the pytest arguments after ``--``) with
``--durations=0`` and a ``sitecustomize`` hook on ``PYTHONPATH`` that makes every Python process the suite starts
append one line at its exit: its CPU seconds, its command line, and which heavy libraries it imported (the
pytest workers are processes too). Prints the wall time, the tests' sum, the longest files and tests, and the
processes grouped by command with their CPU; ``--json`` keeps it all. A measurement, never a test: run it on an
idle machine, and compare runs of one hour, since a shared host drifts by 10-20 % (docs/verification.md).
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
HEAVY = ("torch", "lerobot.datasets.lerobot_dataset", "mujoco", "open3d", "datasets", "torchvision", "ray", "av")
PYTEST = ["-q", "-n", "2", "--dist", "loadfile"]

# Written into a temporary folder put first on PYTHONPATH: Python imports ``sitecustomize`` at start-up.
HOOK = '''import atexit, json, os, sys, time
_start = time.perf_counter()
def _log():
    t = os.times()
    row = {{"pid": os.getpid(), "wall_s": round(time.perf_counter() - _start, 2),
           "cpu_s": round(t.user + t.system, 2), "argv": sys.argv[:6],
           "imports": [m for m in {heavy!r} if m in sys.modules]}}
    with open({log!r}, "a") as f:
        f.write(json.dumps(row) + "\\n")
atexit.register(_log)
'''

DURATION = re.compile(r"\s*([\d.]+)s (setup|call|teardown)\s+(\S+)")


def process_kind(argv: list[str]) -> str:
    """A process's command, short: the module or script and its first argument."""
    words = [Path(a).name if "/" in a else a for a in argv[:2]]
    return " ".join(words) or "?"


def summarise(output: str, rows: list[dict], wall_s: float) -> dict:
    tests = collections.Counter()
    for line in output.splitlines():
        m = DURATION.match(line)
        if m:
            tests[m[3]] += float(m[1])
    files = collections.Counter()
    for name, s in tests.items():
        files[name.split("::")[0]] += s
    kinds: dict[str, dict] = {}
    for r in rows:
        k = kinds.setdefault(process_kind(r["argv"]), {"processes": 0, "cpu_s": 0.0, "with_lerobot": 0})
        k["processes"] += 1
        k["cpu_s"] += r["cpu_s"]
        k["with_lerobot"] += "lerobot.datasets.lerobot_dataset" in r["imports"]
    summary = re.findall(r"\d+ (?:passed|failed|skipped|errors?)", output)
    return {"wall_s": round(wall_s, 1), "outcome": summary, "tests_sum_s": round(sum(tests.values()), 1),
            "files": {f: round(s, 1) for f, s in files.most_common()},
            "tests": {t: round(s, 1) for t, s in tests.most_common(40)},
            "processes": len(rows), "cpu_s": round(sum(r["cpu_s"] for r in rows), 1),
            "with_lerobot": sum("lerobot.datasets.lerobot_dataset" in r["imports"] for r in rows),
            "kinds": dict(sorted(kinds.items(), key=lambda kv: -kv[1]["cpu_s"]))}


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    ours, pytest_args = (argv[:argv.index("--")], argv[argv.index("--") + 1:]) if "--" in argv else (argv, PYTEST)
    p = argparse.ArgumentParser(prog="python -m benchmarks.suite_profile", description=__doc__.split("\n\n")[0])
    p.add_argument("--json", type=Path, help="write the whole profile here")
    a = p.parse_args(ours)
    with tempfile.TemporaryDirectory(prefix="suite_profile_") as tmp:
        log = Path(tmp) / "processes.jsonl"
        (Path(tmp) / "sitecustomize.py").write_text(HOOK.format(heavy=HEAVY, log=str(log)))
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [tmp, os.environ.get("PYTHONPATH")]))}
        start = time.perf_counter()
        proc = subprocess.run([sys.executable, "-m", "pytest", *pytest_args, "--durations=0"], cwd=REPO, env=env,
                              capture_output=True, text=True)
        wall = time.perf_counter() - start
        rows = [json.loads(x) for x in log.read_text().splitlines()] if log.is_file() else []
    result = summarise(proc.stdout, rows, wall)
    result["pytest_args"], result["returncode"] = pytest_args, proc.returncode
    print(f"pytest {' '.join(pytest_args)}: {result['wall_s']:.0f} s wall, {', '.join(result['outcome'])}; "
          f"tests summing to {result['tests_sum_s']:.0f} s")
    print("\n| file | s |\n|---|---|")
    for f, s in list(result["files"].items())[:12]:
        print(f"| {f} | {s:.1f} |")
    print(f"\n{result['processes']} Python processes, {result['cpu_s']:.0f} CPU-s; {result['with_lerobot']} imported "
          "LeRobot's dataset module\n\n| command | processes | CPU-s | with LeRobot |\n|---|---|---|---|")
    for k, v in list(result["kinds"].items())[:15]:
        print(f"| `{k}` | {v['processes']} | {v['cpu_s']:.0f} | {v['with_lerobot']} |")
    if a.json:
        a.json.write_text(json.dumps(result, indent=1))
    return proc.returncode


if __name__ == "__main__":
    raise SystemExit(main())
