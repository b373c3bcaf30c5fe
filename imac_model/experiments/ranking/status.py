"""Where a benchmark's work directory stands (``imac-model ranking --work DIR --status``): the stages
done, each mode's training and gates, the evaluation so far. It only reads, and takes no lock, so it
answers while a run is working there."""

from __future__ import annotations

import json
from pathlib import Path

from imac_data.dataset.output import lock_holder
from imac_model.experiments.ranking.evaluation import evaluated_policies, policy_dir
from imac_model.experiments.ranking.gate import GATED_MODE, read_gates
from imac_model.experiments.ranking.plan import RankingPlan
from imac_model.experiments.stages import REPO_ROOT, StageLog
from imac_model.training.log import progress_line


def status(plan: RankingPlan) -> str:
    """A few lines on ``plan``'s work directory, as its files have it now."""
    # the device, not the preset's name: the checkpoint preset trains on the CPU too
    preset = f"trained on a GPU, {plan.gpu_minutes:g} GPU-minutes a mode" if plan.on_gpu else \
        f"trained on the CPU, {plan.cpu_minutes:g} CPU-minutes a mode"
    pid = lock_holder(plan.work)
    lines = [f"{plan.work}: {preset}; {len(plan.policies)} policies; modes {', '.join(plan.modes)}",
             f"  working on it now: {'a process with PID ' + pid if pid else 'no process'}"]
    totals = StageLog(plan.work / "stages.json").totals()
    lines.append("  stages done: " + (", ".join(f"{stage} ({t['wall_s'] / 60:.0f} min)" for stage, t in totals.items())
                                       or "none yet"))
    for mode in plan.modes:
        run = plan.run_dir(mode)
        said = progress_line(run, None if plan.on_gpu else plan.cpu_budget(mode))
        state = "trained" if (run / "DONE.json").is_file() else "training" if said else "not started"
        lines.append(f"  {mode}: {state}" + (f", {said}" if said else ""))
        gates = read_gates(plan, mode)
        if gates:
            lines.append("    gates (balanced accuracy from chunk 1): " + ", ".join(
                f"{g['budget_minutes']:g} min {g['from_chunk']['0']['balanced_accuracy']:.2f}" for g in gates)
                + (f" (goal {plan.gate_min:g})" if mode == GATED_MODE else ""))
        policies = evaluated_policies(plan, mode)
        done = sum((policy_dir(plan, mode, p) / "closed_loop.json").is_file() for p in policies)
        replayed = (plan.wm_dir(mode) / "replays.json").is_file()
        if done or replayed:
            lines.append(f"    evaluated: {done} of {len(policies)} closed loops"
                         + (", the recorded actions' replays" if replayed else ""))
    lines.append(f"  report: {_report(plan)}")
    return "\n".join(lines)


def _report(plan: RankingPlan) -> str:
    """The report's path and when it was written, or why there is none of this run."""
    results = plan.docs / "results.json"
    if not results.is_file():
        return "not written yet"
    r = json.loads(results.read_text())
    work = Path(r["plan"]["work"])
    if (work if work.is_absolute() else REPO_ROOT / work).resolve() != plan.work.resolve():
        return f"not written yet ({plan.docs} holds the report of {r['plan']['work']})"
    return f"{plan.docs / 'README.md'} (written {r.get('written', 'at an unknown time')})"
