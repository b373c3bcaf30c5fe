"""Stage processes forked from one that has imported the heavy libraries once.

Every ``python -m MODULE ...`` job of an experiment used to start a fresh interpreter that imported torch,
LeRobot and Open3D again: about 4 CPU-seconds a job, most of a short job's cost (docs/ranking.md, "The
stages"). A fork server imports them once (:data:`PRELOAD`) and forks a child per job; the child becomes
a process of its own (its own session, log, working directory and environment) and runs the module as
``python -m`` would. Nothing has run in the server but imports, so no thread pool, GL context or decoder is
forked in use. Jobs whose environment differs from the server's (past :data:`VOLATILE`) start fresh, since a
library reads some variables once, at import.

    python -m imac_model.experiments.forkserver     # the server: requests on stdin, events on stdout
"""

from __future__ import annotations

import atexit
import contextlib
import importlib
import json
import os
import runpy
import select
import subprocess
import sys
import traceback
from pathlib import Path

PRELOAD = ("torch", "lerobot.datasets.lerobot_dataset", "open3d", "imac_data.cli", "imac_model.cli.ranking")
VOLATILE = ("PYTEST_CURRENT_TEST",)  # changes between a session's calls; nothing preloaded reads it
READY_TIMEOUT_S = 120.0


# ---------------------------------------------------------------- the server (its own process)

def _send(event: dict) -> None:
    os.write(1, (json.dumps(event) + "\n").encode())  # unbuffered: a fork must not inherit pending output


def _run_job(job: dict) -> None:
    """In the forked child: become the job's process and run its module; never returns."""
    code = 1
    try:
        os.setsid()
        fd = os.open(job["log"], os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
        os.dup2(fd, 1)
        os.dup2(fd, 2)
        os.close(fd)
        null = os.open(os.devnull, os.O_RDONLY)
        os.dup2(null, 0)
        os.close(null)
        os.chdir(job["cwd"])
        os.environ.clear()
        os.environ.update(job["env"])
        sys.path[0] = job["cwd"]  # as `python -m` puts its working directory first
        sys.argv = [job["module"], *job["args"]]
        try:
            runpy.run_module(job["module"], run_name="__main__", alter_sys=True)
            code = 0
        except SystemExit as e:
            code = e.code if isinstance(e.code, int) else 0 if e.code is None else 1
            if not isinstance(e.code, int | None):
                print(e.code, file=sys.stderr)
        except KeyboardInterrupt:
            code = 130
        except BaseException:
            traceback.print_exc()
        with contextlib.suppress(BaseException):
            atexit._run_exitfuncs()  # what an interpreter's exit would run
    finally:
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(BaseException):
                stream.flush()
        os._exit(code)


def serve() -> None:
    """Import :data:`PRELOAD`, say ``ready``, then fork a child per request line until stdin closes."""
    try:
        for name in PRELOAD:
            importlib.import_module(name)
    except Exception as e:  # noqa: BLE001 - said to the client, which starts its jobs fresh
        _send({"error": f"importing {name}: {type(e).__name__}: {e}"})
        return
    _send({"ready": os.getpid()})
    pending, children, cpu_reported = b"", set(), 0.0
    while True:
        readable, _, _ = select.select([0], [], [], 0.2)
        if readable:
            data = os.read(0, 1 << 16)
            if not data:  # the client has gone; running jobs go on, as processes of their own would
                os._exit(0)  # nothing to finalise: tearing the preloaded libraries down took 1.7 s
            pending += data
            while b"\n" in pending:
                line, pending = pending.split(b"\n", 1)
                job = json.loads(line)
                sys.stdout.flush()
                sys.stderr.flush()
                pid = os.fork()
                if pid == 0:
                    _run_job(job)
                children.add(pid)
                _send({"started": job["id"], "pid": pid})
        for pid in list(children):
            done, status, usage = os.wait4(pid, os.WNOHANG)
            if done:
                children.discard(pid)
                t = os.times()
                mine = t.user + t.system  # the server's own CPU (its imports, its forks) is charged to the jobs
                _send({"exited": pid, "code": os.waitstatus_to_exitcode(status),
                       "cpu_s": usage.ru_utime + usage.ru_stime + mine - cpu_reported})
                cpu_reported = mine


# ---------------------------------------------------------------- the client (the experiment's process)

class ForkedJob:
    """A job forked by the server, read as a ``subprocess.Popen``: ``pid``, ``poll()``, ``returncode``."""

    def __init__(self, server: ForkServer, pid: int):
        self.server, self.pid, self.returncode = server, pid, None

    def poll(self) -> int | None:
        if self.returncode is None:
            self.server.pump()
            if self.returncode is None and not self.server.alive() and not _running(self.pid):
                self.returncode = -1  # the server ended before it could say how the job did
        return self.returncode


def _running(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[-1].split()[0] != "Z"
    except OSError:
        return False


class ForkServer:
    """One server process and the jobs it forked; :func:`server` keeps one per experiment process."""

    def __init__(self, env: dict):
        self.env, self.jobs, self._buf, self._next_id = dict(env), {}, b"", 0
        self.proc = subprocess.Popen([sys.executable, "-m", __name__], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, env=self.env,
                                     cwd=Path(__file__).resolve().parents[2], start_new_session=True)
        event = self._read(timeout=READY_TIMEOUT_S, until=lambda e: "ready" in e or "error" in e)
        if event is None or "error" in event:
            self.close()
            raise OSError(event["error"] if event else "the fork server did not start")

    def same_env(self, env: dict) -> bool:
        strip = lambda e: {k: v for k, v in e.items() if k not in VOLATILE}  # noqa: E731
        return strip(env) == strip(self.env)

    def alive(self) -> bool:
        return self.proc.poll() is None

    def start(self, argv: list[str], log: Path, env: dict) -> ForkedJob:
        """Fork ``argv`` (``python -m MODULE ARGS``) with its output appended to ``log``."""
        self._next_id += 1
        job = {"id": self._next_id, "module": argv[2], "args": list(argv[3:]), "log": str(log),
               "cwd": os.getcwd(), "env": env}
        self.proc.stdin.write((json.dumps(job) + "\n").encode())
        self.proc.stdin.flush()
        event = self._read(timeout=READY_TIMEOUT_S, until=lambda e: e.get("started") == job["id"])
        if event is None:
            raise OSError("the fork server did not start the job")
        self.jobs[event["pid"]] = ForkedJob(self, event["pid"])
        return self.jobs[event["pid"]]

    def pump(self) -> None:
        """Take in whatever events the server has written, without waiting."""
        self._read(timeout=0.0, until=lambda e: False)

    def _read(self, timeout: float, until) -> dict | None:
        global _REAPED_CPU_S
        fd = self.proc.stdout.fileno()
        while True:
            while b"\n" in self._buf:
                line, self._buf = self._buf.split(b"\n", 1)
                event = json.loads(line)
                if "exited" in event:
                    _REAPED_CPU_S += event["cpu_s"]
                    job = self.jobs.pop(event["exited"], None)
                    if job is not None:
                        job.returncode = event["code"]
                if until(event):
                    return event
            readable, _, _ = select.select([fd], [], [], timeout)
            data = os.read(fd, 1 << 16) if readable else b""
            if not data:
                return None
            self._buf += data

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.proc.stdin.close()
        with contextlib.suppress(subprocess.TimeoutExpired):
            self.proc.wait(timeout=5)


_SERVER: ForkServer | None = None
_FAILED = False
_REAPED_CPU_S = 0.0


def server(env: dict) -> ForkServer | None:
    """This process's fork server for jobs in ``env``, started on first use and again when the environment
    changes; None where the job must start fresh (the server for another environment still has jobs
    running, or no server can start here)."""
    global _SERVER, _FAILED
    if _FAILED:
        return None
    if _SERVER is not None and not _SERVER.same_env(env):
        _SERVER.pump()
        if _SERVER.jobs:  # a server whose jobs still run is kept; this job starts fresh
            return None
        _SERVER.close()  # the environment has changed for good: a server for the new one
    if _SERVER is None or not _SERVER.alive() or not _SERVER.same_env(env):
        try:
            _SERVER = ForkServer(env)
        except OSError as e:
            _FAILED = True
            print(f"fork server unavailable ({e}); each job starts a fresh interpreter", file=sys.stderr)
            return None
        atexit.register(_SERVER.close)
    return _SERVER


def forked_cpu_seconds() -> float:
    """CPU seconds of the jobs this process's server forked and saw end (they are not our children)."""
    return _REAPED_CPU_S


if __name__ == "__main__":
    serve()
