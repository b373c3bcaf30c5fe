"""The experiments' subprocess runner (imac_model/experiments/stages.py, run_all): a long stage says how
its jobs are doing, and whatever stops the stage stops its jobs, the processes they started included."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from functools import partial

from imac_model.experiments.stages import REPO_ROOT, run_all
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
    import sys
    from pathlib import Path
    from imac_model.experiments.stages import run_all
    out = Path(sys.argv[1])
    # a job as the stages start them: bash running python, which would outlive bash if bash alone were stopped
    job = ["bash", "-c", f"{sys.executable} -c 'import os, time; open(\\"{out}/pid\\", \\"w\\").write(str(os.getpid())); "
           f"time.sleep(60)' && touch {out}/finished"]
    run_all([("job", job, out / "job.log")], 1, tag="t")
""")


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    with open(f"/proc/{pid}/stat") as f:  # a zombie has ended
        return f.read().split(")")[-1].split()[0] != "Z"


def test_stopping_a_stage_stops_its_jobs_and_what_they_started(tmp_path):
    """SIGTERM (a scheduler, kill) or SIGINT to the stage's process alone: the job's python, started by its
    bash, ends too, rather than go on writing what a rerun would resume from."""
    (tmp_path / "stage.py").write_text(STAGE)
    for sig, code in ((signal.SIGTERM, 143), (signal.SIGINT, -signal.SIGINT)):  # KeyboardInterrupt ends by SIGINT
        out = tmp_path / sig.name
        out.mkdir()
        env = {**os.environ, "PYTHONPATH": str(REPO_ROOT)}
        stage = subprocess.Popen([sys.executable, str(tmp_path / "stage.py"), str(out)], env=env,
                                 stderr=subprocess.PIPE, text=True)
        deadline = time.time() + 60
        while not (out / "pid").is_file() or not (out / "pid").read_text():
            assert time.time() < deadline and stage.poll() is None, stage.stderr.read() if stage.poll() else ""
            time.sleep(0.1)
        job = int((out / "pid").read_text())
        assert _alive(job)
        stage.send_signal(sig)  # to the stage's process only, not its group
        assert stage.wait(timeout=30) == code
        assert "stopping 1 running job(s)" in stage.stderr.read()
        deadline = time.time() + 15
        while _alive(job) and time.time() < deadline:
            time.sleep(0.1)
        assert not _alive(job), f"the job's python {job} outlived the stage ({sig.name})"
        assert not (out / "finished").exists()
