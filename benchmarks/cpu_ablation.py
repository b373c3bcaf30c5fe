"""Ablations on the ranking benchmark's CPU preset: an arm continues the preset's ``motion+contact``
run from one of its checkpoints with one design choice changed, to the same CPU budget as the preset
(``plan.cpu_minutes``, process CPU time, one thread), and is measured by the same early gate (its
held-out training rollouts replayed; balanced accuracy of the lift judge from every chunk). The
baseline is the preset's own run, which continues from the same checkpoint unchanged (a resumed run
draws the same batches and noise), measured by its gate at the end of the budget::

    python -m benchmarks.cpu_ablation rollout --work runs/ranking_cpu --from-step 3800 \\
        --json benchmarks/results/rollout_cpu_ablation.json

The arm lives in ``<work>/runs/<arm>`` (checkpoint, log, gates); an interrupted call resumes. The
GPU preset's ablations, trained side by side on the pack, are :mod:`benchmarks.ablation`."""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

from imac_data.errors import InputError
from imac_model.experiments.ranking.benchmark import internal, train_command
from imac_model.experiments.ranking.gate import GATED_MODE, read_gates
from imac_model.experiments.ranking.plan import RankingPlan
from imac_model.experiments.stages import run_all
from imac_model.training.log import read_log, write_log

ARMS = {  # ablation -> plan -> (the arm's run, what it changes)
    # clips as long as the replays, every chunk after the first from the model's own last frame
    "rollout": lambda plan: (f"motion_contact_rollout{plan.chunks}", {"rollout.chunks": plan.chunks}),
    "reference-noise": lambda plan: ("motion_contact_noise03", {"flow.reference_noise": 0.3}),
}


def branch(plan: RankingPlan, arm: str, from_step: int) -> Path:
    """``<work>/runs/<arm>``: a copy of the preset's motion+contact run at ``from_step`` (its
    checkpoint, the log up to it, its config), unless it exists."""
    base, run = plan.run_dir(GATED_MODE), plan.work / "runs" / arm
    if (run / "branch.json").is_file():
        return run
    source = base / "checkpoints" / f"step_{from_step:06d}"
    if not source.is_dir():
        have = sorted(p.name for p in (base / "checkpoints").glob("step_*"))
        raise InputError(f"--from-step {from_step}: {source} does not exist (the run keeps {have or 'none'})")
    tmp = run.with_name(run.name + ".branching")
    shutil.rmtree(tmp, ignore_errors=True)
    shutil.copytree(source, tmp / "checkpoints" / source.name)
    rows = read_log(base, upto=from_step)
    write_log(tmp, rows)
    (tmp / "branch.json").write_text(json.dumps({"from": str(base.relative_to(plan.work)), "step": from_step,
                                                 "cpu_s": rows[-1].get("cpu_s")}, indent=1) + "\n")
    tmp.rename(run)
    return run


def train_arm(plan: RankingPlan, run: Path, changes: dict) -> None:
    """Train the arm to the preset's CPU budget with ``changes`` (resumes; marks it trained)."""
    if (run / "DONE.json").is_file():
        return
    argv = train_command(plan, GATED_MODE, changes={"train.output_dir": str(run), **changes})
    run_all([(f"train {run.name}", argv, plan.work / "logs" / f"train_{run.name}.log")], 1, tag="ablation")


def final_gate(plan: RankingPlan, run_name: str, from_step: int) -> dict | None:
    """The run's gate at the end of the budget, of a checkpoint at or after ``from_step``."""
    return next((g for g in reversed(read_gates(plan, run_name))
                 if g["budget_minutes"] == plan.cpu_minutes and g["step"] >= from_step), None)


def ablate(plan: RankingPlan, ablation: str, from_step: int) -> dict:
    arm, changes = ARMS[ablation](plan)
    run = branch(plan, arm, from_step)
    train_arm(plan, run, changes)
    if final_gate(plan, arm, from_step) is None:
        run_all([(f"gate {arm}", internal(plan, "gate", f"{plan.cpu_minutes:g}", arm),
                  plan.work / "logs" / f"gate_{arm}.log")], 1, tag="ablation")
    baseline = final_gate(plan, GATED_MODE, from_step)
    if baseline is None:
        raise InputError(f"{plan.work}: motion+contact has no gate at {plan.cpu_minutes:g} CPU-minutes after step "
                         f"{from_step} yet; run the CPU preset to the end of its budget (imac-model ranking --work "
                         f"{plan.work}), then this again")
    batch = plan.run_config(GATED_MODE).train.batch_size
    result = {"ablation": ablation, "changes": changes, "from_step": from_step, "cpu_minutes": plan.cpu_minutes}
    for name, gate in (("baseline", baseline), ("arm", final_gate(plan, arm, from_step))):
        run_name = arm if name == "arm" else plan.run_dir(GATED_MODE).name
        rows = read_log(plan.work / "runs" / run_name)
        chunks_per_step = batch * int(changes.get("rollout.chunks", 1)) if name == "arm" else batch
        result[name] = {"run": run_name, "step": gate["step"], "chunks": (gate["step"] - from_step) * chunks_per_step,
                        "balanced_accuracy_from_chunk": {k: v["balanced_accuracy"]
                                                         for k, v in gate["from_chunk"].items()},
                        "cube_at_chunk_end": gate.get("cube_at_chunk_end"),
                        "heldout_loss": next((r["heldout_loss"] for r in reversed(rows) if "heldout_loss" in r),
                                             None)}
    return result


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("ablation", choices=sorted(ARMS))
    p.add_argument("--work", default="runs/ranking_cpu", help="the CPU preset's work directory")
    p.add_argument("--from-step", type=int, required=True, help="the checkpoint of motion+contact the arm starts from")
    p.add_argument("--json", help="write the figures here")
    args = p.parse_args(argv)
    plan = RankingPlan.load(Path(args.work) / "plan.json")
    result = ablate(plan, args.ablation, args.from_step)
    for name in ("baseline", "arm"):
        r = result[name]
        gate = " ".join(f"{x:.2f}" for x in r["balanced_accuracy_from_chunk"].values())
        print(f"{name:8s} {r['run']}: step {r['step']}, {r['chunks']} chunks trained after step {args.from_step}; "
              f"gate from chunk 1.. {gate}; held-out loss {r['heldout_loss']:.4f}; cube at each chunk's end "
              f"{r['cube_at_chunk_end']}")
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
