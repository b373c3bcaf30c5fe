"""What the experiments share: each stage's wall and CPU seconds, subprocesses run a few at a
time with their logs, a marker file for finished work. A stage that finds its outputs skips
its work, so an interrupted experiment resumes where it stopped."""

from __future__ import annotations

import contextlib
import json
import os
import platform
import resource
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import torch

from imac_model.experiments import forkserver

REPO_ROOT = Path(__file__).resolve().parents[2]


def python() -> list[str]:
    """The interpreter of this process, for subprocesses."""
    return [sys.executable]


def subprocess_env() -> dict:
    """This environment with the repository importable and MuJoCo on EGL (unless set)."""
    env = dict(os.environ)
    root = str(REPO_ROOT)
    env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    env.setdefault("MUJOCO_GL", "egl")
    env.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    return env


def cpu_seconds() -> float:
    """User + system CPU seconds of this process and its finished children, those forked for it included."""
    s, c = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return s.ru_utime + s.ru_stime + c.ru_utime + c.ru_stime + forkserver.forked_cpu_seconds()


class StageLog:
    """Wall and CPU seconds (this process and its children) and load averages per stage,
    appended to a JSON file (an interrupted-and-resumed stage has several entries)."""

    def __init__(self, path: Path, tag: str = "experiment"):
        self.path, self.tag = path, tag
        self.entries = json.loads(path.read_text()) if path.is_file() else []

    def run(self, stage: str, fn: Callable[[], None]) -> None:
        w0, c0, load0 = time.time(), cpu_seconds(), os.getloadavg()
        print(f"[{self.tag}] {stage}: start (load average {load0[0]:.2f})", file=sys.stderr, flush=True)
        fn()
        entry = {"stage": stage, "wall_s": round(time.time() - w0, 2), "cpu_s": round(cpu_seconds() - c0, 2),
                 "load_start": [round(x, 2) for x in load0], "load_end": [round(x, 2) for x in os.getloadavg()],
                 "finished": time.strftime("%Y-%m-%d %H:%M:%S"), "commit": git("describe", "--always", "--dirty")}
        self.entries.append(entry)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.path.write_text(json.dumps(self.entries, indent=1))
        print(f"[{self.tag}] {stage}: done in {entry['wall_s']:.0f} s wall, {entry['cpu_s']:.0f} s CPU",
              file=sys.stderr, flush=True)

    def totals(self) -> dict[str, dict[str, float]]:
        """Per stage: wall and CPU seconds summed over its entries, and the commits they ran at."""
        out: dict[str, dict] = {}
        for e in self.entries:
            t = out.setdefault(e["stage"], {"wall_s": 0.0, "cpu_s": 0.0, "commits": []})
            t["wall_s"] += e["wall_s"]
            t["cpu_s"] += e["cpu_s"]
            commit = e.get("commit", "not recorded")
            if commit not in t["commits"]:
                t["commits"].append(commit)
        return out


HEARTBEAT_S = 300.0  # how often run_all says how its long jobs are doing
STOP_GRACE_S = 10.0  # how long stopped jobs get to end on their own before they are killed


def run_all(commands: list[tuple], jobs: int, tag: str = "experiment", heartbeat_s: float = HEARTBEAT_S) -> None:
    """Run ``(name, argv or Job, log file[, progress])`` subprocesses, ``jobs`` at a time; raise if one fails
    (or its :attr:`Job.on_success` does).
    Every ``heartbeat_s`` each running job gets a line: how long it has run and, where it has a
    ``progress`` callable, what that returns (a training run's step and budget), so an hours-long
    stage is not silent. Each job runs in a process group of its own, and whatever stops this process
    (Ctrl-C, SIGTERM, an error) stops its running jobs with it: a job left running would go on writing
    the checkpoints that the rerun resumes from."""
    pending, running, failed = [tuple(c) + (None,) * (4 - len(c)) for c in commands], [], []
    next_beat = time.time() + heartbeat_s
    terminate = _terminate_on_sigterm()
    try:
        while pending or running:
            while pending and len(running) < jobs:
                name, job, log, progress = pending.pop(0)
                job = job if isinstance(job, Job) else Job(list(job))
                log.parent.mkdir(parents=True, exist_ok=True)
                f = open(log, "a")
                proc = _start(job.argv, f, log)
                running.append((name, proc, f, log, progress, time.time(), job))
                print(f"[{tag}]   started {name} (log {log})", file=sys.stderr, flush=True)
            time.sleep(min(0.5, heartbeat_s))
            for item in list(running):
                name, proc, f, log, _, _, job = item
                if proc.poll() is not None:
                    f.close()
                    running.remove(item)
                    if proc.returncode:
                        failed.append(f"{name} (exit {proc.returncode}, log {log})")
                    elif job.on_success is not None:
                        try:
                            job.on_success()
                        except (OSError, ValueError, IndexError) as e:  # e.g. a training run that logged no step
                            failed.append(f"{name} (finished, but marking it done failed: {e}; log {log})")
                    print(f"[{tag}]   finished {name} (exit {proc.returncode})", file=sys.stderr, flush=True)
            if running and time.time() >= next_beat:
                next_beat = time.time() + heartbeat_s
                for name, _, _, _, progress, started, _ in running:
                    said = _progress(progress)
                    print(f"[{tag}]   {name}: {(time.time() - started) / 60:.0f} min" + (f", {said}" if said else ""),
                          file=sys.stderr, flush=True)
    except BaseException:
        _stop([item[1] for item in running], tag)
        raise
    finally:
        for item in running:
            item[2].close()
        terminate()
    if failed:
        raise RuntimeError("failed: " + "; ".join(failed))


def _start(argv: list[str], f, log: Path):
    """A job in a process of its own: ``python -m`` jobs forked from the fork server (their imports done
    once: docs/ranking.md, "The stages"), any other a fresh process."""
    env = subprocess_env()
    server = forkserver.server(env) if list(argv[:2]) == [*python(), "-m"] and len(argv) > 2 else None
    if server is not None:
        with contextlib.suppress(OSError):  # the server has gone (killed): this job starts fresh
            return server.start(argv, log, env)
    return subprocess.Popen(argv, stdout=f, stderr=subprocess.STDOUT, env=env, start_new_session=True)


def _terminate_on_sigterm() -> Callable[[], None]:
    """SIGTERM ends this process as an exception (exit 143) while jobs run, so that they are stopped
    too; returns what puts the previous handler back."""
    if threading.current_thread() is not threading.main_thread():
        return lambda: None

    def handler(signum, frame):
        raise SystemExit(128 + signum)

    previous = signal.signal(signal.SIGTERM, handler)
    return lambda: signal.signal(signal.SIGTERM, previous)


def _stop(procs: list[subprocess.Popen], tag: str) -> None:
    """Stop jobs as a terminal's Ctrl-C would (SIGINT to each one's process group: a job and the
    processes it started), and kill those still running after STOP_GRACE_S."""
    alive = [p for p in procs if p.poll() is None]
    if alive:
        print(f"[{tag}]   stopping {len(alive)} running job(s)", file=sys.stderr, flush=True)
    for sig in (signal.SIGINT, signal.SIGKILL):
        for p in alive:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(p.pid, sig)
        deadline = time.time() + STOP_GRACE_S
        while alive and time.time() < deadline:
            alive = [p for p in alive if p.poll() is None]
            time.sleep(0.1)
        if not alive:
            return


def _progress(progress: Callable[[], str | None] | None) -> str | None:
    """What a job's progress callable says; a heartbeat never stops the jobs (a log being written
    can be read half-way)."""
    try:
        return progress() if progress else None
    except (OSError, ValueError, KeyError, TypeError):
        return None


@dataclass(frozen=True)
class Job:
    """A command for :func:`run_all`, and what this process does once it has succeeded (write the marker that
    counts its work as done). Here rather than in a shell after it, so that a ``python -m`` job is forked from
    the fork server, whose children run one module each."""

    argv: list[str]
    on_success: Callable[[], None] | None = None


def then_mark_done(argv: list[str], marker: Path) -> Job:
    """``argv``, and on success a marker file: the work is counted as done only then."""
    return Job(list(argv), partial(Path(marker).touch))



def git(*args: str) -> str:
    """``git ARGS`` in the repository ("unknown" outside a clone)."""
    try:
        return subprocess.run(["git", *args], cwd=REPO_ROOT, capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def machine() -> dict:
    """Cores, CPU, memory and versions: what a report's figures were measured on."""
    cpu = "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    mem = None
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal"):
                mem = round(int(line.split()[1]) / 1024**2, 1)
    except OSError:
        pass
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return {"cores": cores, "cpu": cpu, "memory_gb": mem, "python": platform.python_version(),
            "torch": torch.__version__, "gpu": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
            "load_average_at_report": [round(x, 2) for x in os.getloadavg()]}


def mark_trained(run: Path) -> None:
    """After ``imac-model train``: the run's last log row as ``DONE.json``, marking the run as finished."""
    rows = [json.loads(line) for line in (Path(run) / "log.jsonl").read_text().splitlines() if line.strip()]
    (Path(run) / "DONE.json").write_text(json.dumps(rows[-1]))


def train_job(config: str | Path, overrides: dict, finish: bool = True) -> Job:
    """``imac-model train --config CONFIG`` with ``overrides`` set (resuming the run's checkpoints); with
    ``finish``, the run is then marked trained (:func:`mark_trained`)."""
    sets = [a for k, v in overrides.items() for a in ("--set", f"{k}={json.dumps(v)}")]
    argv = python() + ["-m", "imac_model", "train", "--config", str(config), "--no-progress", *sets]
    return Job(argv, partial(mark_trained, Path(overrides["train.output_dir"])) if finish else None)
