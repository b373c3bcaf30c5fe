"""A run's training log (imac_model/training/log.py): a training run's progress, read from its log."""

from __future__ import annotations

from imac_model.training.log import progress_line, write_log


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
    # a run trained on a GPU is budgeted in wall minutes; its process's CPU time says nothing of the budget
    write_log(run, [{"step": 1410, "loss": 0.125, "cpu_s": 113.0, "wall_s": 114.0, "device": "NVIDIA H200"}])
    assert progress_line(run) == "step 1,410, 1.9 wall minutes on NVIDIA H200, loss 0.125"
