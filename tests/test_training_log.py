"""A run's training log (imac_model/training/log.py): a run continued from another's last weights
(the GPU preset's INIT) reads as one run, its steps and samples going on from the first's end; a
long stage reads its runs' logs to say how far they are."""

from __future__ import annotations

import sys
from functools import partial

from imac_model.experiments.stages import run_all
from imac_model.training.log import continued_log, progress_line, write_log


def _gpu_log(steps: int, samples_per_step: int, train_s: float, heldout: float) -> list[dict]:
    rows = [{"step": s, "loss": 1.0 / s, "samples": s * samples_per_step, "elapsed_s": train_s * s / steps}
            for s in range(50, steps + 1, 50)]
    return [*rows, {"summary": {"steps": steps, "samples": steps * samples_per_step, "train_s": train_s,
                                "heldout_loss": heldout}}]


def test_a_continued_run_counts_from_where_the_first_ended():
    first, second, third = _gpu_log(100, 512, 60.0, 0.07), _gpu_log(150, 256, 90.0, 0.06), _gpu_log(50, 256, 30.0, 0.05)
    rows = continued_log(continued_log(first, second), third)
    steps = [r["step"] for r in rows if "step" in r]
    assert steps == [50, 100, 150, 200, 250, 300]  # 100 + (50, 100, 150), then 250 + 50
    assert [r.get("part", 1) for r in rows if "step" in r] == [1, 1, 2, 2, 2, 3]
    assert [r["samples"] for r in rows if "step" in r][2:] == [51200 + 12800, 51200 + 25600, 51200 + 38400,
                                                               51200 + 38400 + 12800]
    assert rows[3]["elapsed_s"] == 60.0 + 60.0
    summary = rows[-1]["summary"]
    assert (summary["steps"], summary["samples"], summary["train_s"]) == (300, 51200 + 38400 + 12800, 180.0)
    assert summary["heldout_loss"] == 0.05  # the last part's model is the run's
    assert [p["steps"] for p in summary["parts"]] == [100, 150, 50]
    assert sum("summary" in r for r in rows) == 1 and "summary" in rows[-1]


def test_a_long_stage_says_how_its_training_run_is_doing(tmp_path, capsys):
    """run_all's heartbeat: a job still running gets a line with what its progress callable reads
    from the run's log (step, CPU-minutes of the budget, losses); a job without one, its time."""
    run = tmp_path / "run"
    write_log(run, [{"step": 10, "loss": 0.5, "cpu_s": 30.0}, {"step": 20, "loss": 0.25, "heldout_loss": 0.3, "cpu_s": 60.0},
                    {"step": 30, "loss": 0.125, "cpu_s": 90.0}])
    assert progress_line(run, 60) == "step 30, 1.5 of 60 CPU-minutes, loss 0.125, held-out 0.3 (step 20)"
    assert progress_line(tmp_path / "none yet", 60) is None
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
