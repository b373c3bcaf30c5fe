"""The experiments' subprocess runner (imac_model/experiments/stages.py, run_all): a long stage says how
its jobs are doing, and whatever stops the stage stops its jobs, the processes they started included."""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from functools import partial

import pytest

from imac_model.experiments import forkserver
from imac_model.experiments.stages import REPO_ROOT, cpu_seconds, run_all, subprocess_env, then_mark_done, train_job
from imac_model.training.log import progress_line, write_log


def test_a_long_stage_says_how_its_training_run_is_doing(tmp_path, capsys):
    """run_all's heartbeat: a job still running gets a line with what its progress callable reads
    from the run's log (step, CPU-minutes of the budget, losses); a job without one, its time."""
    run = tmp_path / "run"
    (run).mkdir()
    (run / "log.jsonl").write_text('{"step": 1, "lo')  # half-written: a heartbeat must not stop the jobs
    sleep = [sys.executable, "-c", "import time; time.sleep(1.2)"]
    run_all([("train", sleep, tmp_path / "train.log", partial(progress_line, run, 60)),
             ("gate", sleep, tmp_path / "gate.log")], 2, tag="t", heartbeat_s=0.4)
    lines = capsys.readouterr().err.splitlines()
    assert any(line.startswith("[t]   gate: 0 min") for line in lines)
    assert any(line == "[t]   train: 0 min" for line in lines)  # the log half-written: its time alone
    write_log(run, [{"step": 40, "loss": 0.1, "cpu_s": 120.0}])
    run_all([("train", sleep, tmp_path / "train.log", partial(progress_line, run, 60))], 1, tag="t", heartbeat_s=0.4)
    assert "[t]   train: 0 min, step 40, 2.0 of 60 CPU-minutes, loss 0.1" in capsys.readouterr().err.splitlines()


STAGE = textwrap.dedent("""
    import os
    import sys
    from pathlib import Path
    from imac_model.experiments.stages import run_all
    out = Path(sys.argv[1])
    # a job as the stages start them: bash running python, which would outlive bash if bash alone were stopped
    job = ["bash", "-c", f"{sys.executable} -c 'import os, time; open(\\"{out}/pid\\", \\"w\\").write(str(os.getpid())); "
           f"time.sleep(60)' && touch {out}/finished"]
    if sys.argv[2] == "forked":  # a `python -m` job: forked from the fork server, not run_all's child
        (out / "waiter.py").write_text("import os, time; open('pid', 'w').write(str(os.getpid())); time.sleep(60); "
                                       "open('finished', 'w')")
        os.chdir(out)
        job = [sys.executable, "-m", "waiter"]
    run_all([("job", job, out / "job.log")], 1, tag="t")
""")


def test_a_training_job_is_marked_trained_by_its_last_log_row_and_only_on_success(tmp_path):
    """train_job's run is marked trained (DONE.json: the log's last row) once the job has succeeded; a job whose
    marking fails (a run that logged no step) fails the stage, naming the job and its log."""
    run = tmp_path / "run"
    job = train_job("config.yaml", {"train.output_dir": str(run), "train.max_cpu_minutes": 1.0})
    assert job.argv[1:5] == ["-m", "imac_model", "train", "--config"]
    assert job.argv[-2:] == ["--set", "train.max_cpu_minutes=1.0"]
    assert train_job("config.yaml", {"train.output_dir": str(run)}, finish=False).on_success is None
    ok = dataclasses.replace(job, argv=[sys.executable, "-c", "pass"])
    with pytest.raises(RuntimeError, match=f"train \\(finished, but marking it done failed: .*log {tmp_path}/t.log"):
        run_all([("train", ok, tmp_path / "t.log")], 1, tag="t")
    write_log(run, [{"step": 1, "loss": 0.5}, {"step": 2, "loss": 0.25}])
    run_all([("train", ok, tmp_path / "t.log")], 1, tag="t")
    assert json.loads((run / "DONE.json").read_text()) == {"step": 2, "loss": 0.25}
    failing = dataclasses.replace(job, argv=[sys.executable, "-c", "raise SystemExit(2)"])
    (run / "DONE.json").unlink()
    with pytest.raises(RuntimeError, match="train \\(exit 2"):
        run_all([("train", failing, tmp_path / "t.log")], 1, tag="t")
    assert not (run / "DONE.json").exists()


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    with open(f"/proc/{pid}/stat") as f:  # a zombie has ended
        return f.read().split(")")[-1].split()[0] != "Z"


def test_stopping_a_stage_stops_its_jobs_and_what_they_started(tmp_path):
    """SIGTERM (a scheduler, kill) or SIGINT to the stage's process alone: the job's python, started by its
    bash or forked from the fork server, ends too, rather than go on writing what a rerun would resume from."""
    (tmp_path / "stage.py").write_text(STAGE)
    for sig, kind in ((signal.SIGTERM, "bash"), (signal.SIGINT, "bash"), (signal.SIGTERM, "forked")):
        code = 143 if sig == signal.SIGTERM else -signal.SIGINT  # KeyboardInterrupt ends by SIGINT
        out = tmp_path / f"{sig.name}_{kind}"
        out.mkdir()
        env = {**os.environ, "PYTHONPATH": str(REPO_ROOT)}
        stage = subprocess.Popen([sys.executable, str(tmp_path / "stage.py"), str(out), kind], env=env,
                                 stderr=subprocess.PIPE, text=True)
        deadline = time.time() + 60
        while not (out / "pid").is_file() or not (out / "pid").read_text():
            assert time.time() < deadline and stage.poll() is None, stage.stderr.read() if stage.poll() else ""
            time.sleep(0.1)
        job = int((out / "pid").read_text())
        assert _alive(job)
        with open(f"/proc/{job}/stat") as f:
            parent = int(f.read().rsplit(")", 1)[1].split()[1])
        with open(f"/proc/{parent}/cmdline") as f:
            assert ("imac_model.experiments.forkserver" in f.read()) == (kind == "forked")
        stage.send_signal(sig)  # to the stage's process only, not its group
        assert stage.wait(timeout=30) == code
        assert "stopping 1 running job(s)" in stage.stderr.read()
        deadline = time.time() + 15
        while _alive(job) and time.time() < deadline:
            time.sleep(0.1)
        assert not _alive(job), f"the job's python {job} outlived the stage ({sig.name}, {kind})"
        assert not (out / "finished").exists()


PROBE = textwrap.dedent("""
    import json, os, sys
    print(json.dumps({"name": __name__, "argv": sys.argv[1:], "cwd": os.getcwd(), "path0": sys.path[0],
                      "env": os.environ.get("PROBE_VALUE"), "stdin": sys.stdin.read()}))
    print("to stderr", file=sys.stderr)
    print(os.getppid(), os.getsid(0) == os.getpid(), file=open("ids", "w"))
    if sys.argv[1] == "fail":
        raise ValueError("the probe failed")
    sys.exit(int(sys.argv[1]))
""")


def test_a_forked_job_runs_as_a_fresh_interpreter_would(tmp_path, monkeypatch):
    """A ``python -m`` job of run_all is forked from the fork server (imac_model/experiments/forkserver.py); the
    oracle is the same command run by a fresh interpreter: the same output, exit code, working directory and
    path, in a session of its own, with this process's environment, and its CPU counted by cpu_seconds.
    A library reads some variables once, at import, so a server serves one environment: a job in another
    starts fresh while the old server's jobs run, and is forked from a new server once they have ended."""
    (tmp_path / "probe_module.py").write_text(PROBE)
    monkeypatch.chdir(tmp_path)  # `python -m` finds the module in the working directory
    monkeypatch.setenv("PROBE_VALUE", "seen")
    for code in ("0", "3", "fail"):
        argv = [sys.executable, "-m", "probe_module", code, "two words"]
        fresh = subprocess.run(argv, env=subprocess_env(), capture_output=True, text=True, stdin=subprocess.DEVNULL)
        log = tmp_path / f"job_{code}.log"
        log.write_text("before\n")  # a log is appended to, as by a fresh process
        before = cpu_seconds()
        marked = then_mark_done(argv, tmp_path / f"done_{code}")  # its marker written by run_all, not a shell
        if code == "0":
            run_all([("probe", marked, log)], 1, tag="t")
        else:
            with pytest.raises(RuntimeError, match=f"probe \\(exit {1 if code == 'fail' else 3}, log {log}\\)"):
                run_all([("probe", marked, log)], 1, tag="t")
        assert (tmp_path / f"done_{code}").is_file() == (code == "0")
        server = forkserver.server(subprocess_env())
        parent, own_session = (tmp_path / "ids").read_text().split()
        assert server is not None and int(parent) == server.proc.pid and own_session == "True"
        assert cpu_seconds() > before  # the job's CPU, though the job was the server's child
        out = log.read_text()
        assert out.startswith("before\n" + fresh.stdout)
        assert json.loads(fresh.stdout)["env"] == "seen" and json.loads(fresh.stdout)["argv"] == [code, "two words"]
        assert ("ValueError: the probe failed" in out) == (code == "fail") == ("ValueError" in fresh.stderr)
        assert "to stderr" in out

    (tmp_path / "sleeper.py").write_text("import time; time.sleep(1.0)")
    old = forkserver.server(subprocess_env())
    sleeping = old.start([sys.executable, "-m", "sleeper"], tmp_path / "sleep.log", subprocess_env())
    monkeypatch.setenv("PROBE_VALUE", "another")
    assert forkserver.server(subprocess_env()) is None  # the old server's job runs
    run_all([("probe", [sys.executable, "-m", "probe_module", "0"], tmp_path / "a.log")], 1, tag="t")
    assert int((tmp_path / "ids").read_text().split()[0]) == os.getpid()  # a fresh process, run_all's child
    assert json.loads((tmp_path / "a.log").read_text().splitlines()[0])["env"] == "another"
    deadline = time.time() + 30
    while sleeping.poll() is None:
        assert time.time() < deadline
        time.sleep(0.1)
    assert sleeping.returncode == 0
    run_all([("probe", [sys.executable, "-m", "probe_module", "0"], tmp_path / "b.log")], 1, tag="t")
    new = forkserver.server(subprocess_env())
    assert new is not old and not old.alive() and new.alive()
    assert int((tmp_path / "ids").read_text().split()[0]) == new.proc.pid
    assert json.loads((tmp_path / "b.log").read_text().splitlines()[0])["env"] == "another"
