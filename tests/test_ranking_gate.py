"""The early gate's arithmetic (imac_model/experiments/ranking/gate.py): when it measures, what it
scores, when it stops. Its run on a trained model is in tests/test_ranking.py (the toy benchmark)."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from imac_data.dataset.output import output_lock
from imac_data.errors import InputError
from imac_model.cli import main as model_main
from imac_model.data import mosaic
from imac_model.evaluate.success import verdict_scores
from imac_model.experiments.ranking.gate import cube_in_view, cube_summary, gate_minutes, gate_verdict
from imac_model.experiments.ranking.plan import RankingPlan


def test_balanced_accuracy_is_the_mean_recall_of_the_outcomes_present():
    rng = np.random.default_rng(0)
    for _ in range(50):
        n = int(rng.integers(1, 30))
        labels, predicted = rng.random(n) < rng.random(), rng.random(n) < 0.5
        recalls = []  # brute force, one outcome at a time
        for outcome in (True, False):
            rows = [p == outcome for p, y in zip(predicted, labels) if y == outcome]
            if rows:
                recalls.append(sum(rows) / len(rows))
        s = verdict_scores(predicted.tolist(), labels.tolist())
        assert s["balanced_accuracy"] == pytest.approx(sum(recalls) / len(recalls))
        assert s["accuracy"] == pytest.approx(float(np.mean(predicted == labels)))
    # painting one outcome everywhere scores 0.5, whatever the mix
    assert verdict_scores([True] * 10, [True] * 7 + [False] * 3)["balanced_accuracy"] == 0.5
    with pytest.raises(InputError, match="3 labels for 2 verdicts"):
        verdict_scores([True, False], [True, False, True])


def _gate(budget: float, score: float) -> dict:
    return {"budget_minutes": budget, "from_chunk": {"0": {"balanced_accuracy": score}}}


def test_the_gate_measures_every_hour_and_stops_after_three_without_a_pass(tmp_path):
    plan = RankingPlan(work=tmp_path, docs=tmp_path)
    assert (plan.cpu_minutes, plan.gate_every, plan.gate_min, plan.gate_by) == (120, 60, 0.7, 180)
    assert gate_minutes(plan) == [60, 120]
    three_hours = dataclasses.replace(plan, cpu_minutes=180)
    assert gate_minutes(three_hours) == [60, 120, 180]
    assert gate_minutes(dataclasses.replace(plan, cpu_minutes=150)) == [60, 120, 150]
    assert gate_minutes(dataclasses.replace(plan, gate_every=None)) == []
    assert gate_verdict(three_hours, [_gate(60, 0.5)]) == "continue"
    assert gate_verdict(three_hours, [_gate(60, 0.5), _gate(120, 0.6)]) == "continue"
    assert gate_verdict(three_hours, [_gate(60, 0.5), _gate(120, 0.7)]) == "passed"
    assert gate_verdict(three_hours, [_gate(60, 0.5), _gate(120, 0.6), _gate(180, 0.69)]) == "stop"
    # a budget below the deadline (the default's): the end of the budget is the deadline
    assert gate_verdict(plan, [_gate(60, 0.5), _gate(120, 0.6)]) == "stop"
    assert gate_verdict(dataclasses.replace(plan, cpu_minutes=150), [_gate(150, 0.6)]) == "stop"
    with pytest.raises(InputError, match="gate_every"):
        RankingPlan(work=tmp_path, docs=tmp_path, gate_every=0)


def test_a_second_run_on_the_same_work_directory_is_refused(tmp_path, capsys):
    """Two benchmark processes on one work directory would train the same checkpoints: the second
    is refused (exit 3, the environment) before it writes anything there."""
    work = tmp_path / "work"
    with output_lock(work):  # as a running benchmark holds it
        code = model_main(["ranking", "--toy", "--work", str(work), "--docs", str(tmp_path / "docs"),
                           "--stages", "report"])
    assert code == 3 and "is writing" in capsys.readouterr().err
    assert not (work / "plan.json").exists()


def test_the_cube_is_found_in_the_view_asked_for_only():
    """cube_in_view against painted rectangles of known area and centre: red in the view asked for
    counts; red in the other view or in the depth row, and a faint red below the threshold, do not."""
    h, w, T = 12, 16, 3
    spec = SimpleNamespace(views=("cam_right_wrist", "cam_workspace"))  # the workspace view second: looked up
    rgb, depth = torch.full((T, 2, 3, h, w), 0.3), torch.full((T, 2, 3, h, w), 0.3)
    boxes = [(2, 4, 5, 6), (7, 1, 3, 3)]  # row, col, height, width
    for t, (r, c, a, b) in enumerate(boxes):
        rgb[t, 1, :, r:r + a, c:c + b] = torch.tensor([0.9, 0.1, 0.1])[:, None, None]
    rgb[:, 0, :, :4, :4] = torch.tensor([1.0, 0.0, 0.0])[:, None, None]  # the wrist view's red
    depth[:, 1, 0] = 1.0  # a red depth colour
    rgb[:, 1, :, 10:, 12:] = torch.tensor([0.45, 0.35, 0.35])[:, None, None]  # redness 0.1
    got = cube_in_view(mosaic.assemble(rgb, depth), spec, "cam_workspace")
    for (r, c, a, b), (n, cy, cx) in zip(boxes, got):
        assert (n, cy, cx) == (a * b, r + (a - 1) / 2, c + (b - 1) / 2)
    assert got[2] == [0, None, None]
    assert cube_in_view(mosaic.assemble(rgb, depth), spec, "cam_right_wrist") == [[16, 1.5, 1.5]] * T


def test_the_cube_summary_counts_kept_cubes_and_their_offsets():
    cube = {"recorded": [[[20, 5, 5], [20, 5, 5], [0, None, None]], [[10, 1, 1], [10, 2, 2], [10, 3, 3]], [[8, 0, 0]]],
            "generated": [[[20, 5, 8], [9, 5, 5], [5, 0, 0]], [[5, 4, 5], [0, None, None], [4, 3, 3]], [[3, 0, 1]]]}
    s = cube_summary(cube)
    # chunk 1: 20>=10, 5>=5, 3<4; chunk 2: 9<10, 0<5; chunk 3: only replay 2's recording shows it (4<5)
    assert s["kept"] == [round(2 / 3, 4), 0.0, 0.0]
    assert s["offset_px"] == [3.0, 0.0, 0.0]  # median of 3, 5, 1; replay 1 alone; replay 2 alone
    assert cube_summary({"recorded": [], "generated": []}) == {"kept": [], "offset_px": []}
