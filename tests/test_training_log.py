"""A run's training log (imac_model/training/log.py): a run continued from another's last weights
(the GPU preset's INIT) reads as one run, its steps and samples going on from the first's end; a
training run's progress, read from its log."""

from __future__ import annotations

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



def test_a_runs_progress_is_read_from_its_log(tmp_path):
    run = tmp_path / "run"
    write_log(run, [{"step": 10, "loss": 0.5, "cpu_s": 30.0}, {"step": 20, "loss": 0.25, "heldout_loss": 0.3, "cpu_s": 60.0},
                    {"step": 30, "loss": 0.125, "cpu_s": 90.0}])
    assert progress_line(run, 60) == "step 30, 1.5 of 60 CPU-minutes, loss 0.125, held-out 0.3 (step 20)"
    assert progress_line(run) == "step 30, 1.5 CPU-minutes, loss 0.125, held-out 0.3 (step 20)"
    # with its wall time: what is left of the budget at the CPU a wall second it has had (here half a core)
    write_log(run, [{"step": 30, "loss": 0.125, "cpu_s": 90.0, "wall_s": 180.0}])
    assert progress_line(run, 60) == "step 30, 1.5 of 60 CPU-minutes (about 117 min to go), loss 0.125"
    assert progress_line(tmp_path / "none yet", 60) is None
