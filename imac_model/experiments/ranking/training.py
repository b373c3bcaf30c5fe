"""The ranking benchmark's ``train`` stage on the CPU: one world model per conditioning mode, the same
CPU budget each, the gated mode first in segments, each followed by the early gate (:mod:`.gate`).
The GPU preset trains its compared modes from the pack instead (:mod:`.gpu`); ``none`` trains here."""

from __future__ import annotations

import sys
from functools import partial

from imac_model.experiments.ranking.datasets import training_side
from imac_model.experiments.ranking.gate import gate_minutes, gate_verdict, read_gates
from imac_model.experiments.ranking.gpu import train_on_gpu
from imac_model.experiments.ranking.plan import GATED_MODE, RankingPlan, internal, slug
from imac_model.experiments.ranking.report import write_report
from imac_model.experiments.stages import Job, run_all, train_job
from imac_model.training.log import progress_line


def train_command(plan: RankingPlan, mode: str, minutes: float | None = None, finish: bool = True,
                  changes: dict | None = None) -> Job:
    """The job training ``mode`` (resuming its checkpoints) up to ``minutes`` CPU-minutes (default: its
    budget); with ``finish``, the run is then marked trained (``DONE.json``). ``changes``: run-config
    fields set on top (an ablation's arm: its output directory and the one setting it changes)."""
    overrides = {**plan.mode_overrides(mode), **(changes or {})}
    if minutes is not None:
        overrides["train.max_cpu_minutes"] = minutes
    return train_job(plan.config, overrides, finish)


class GateStop(RuntimeError):
    """The early gate was not passed in time: the benchmark stops (the report says what it showed)."""


def train_gated(plan: RankingPlan) -> None:
    """motion+contact in segments of ``gate_every`` CPU-minutes, each followed by the early gate
    (:mod:`.gate`); raises :class:`GateStop` when the gate says stop."""
    mode, log = GATED_MODE, plan.work / "logs" / f"train_{slug(GATED_MODE)}.log"
    measured = {g["budget_minutes"] for g in read_gates(plan)}
    for minutes in gate_minutes(plan):
        if minutes not in measured:
            last = minutes == gate_minutes(plan)[-1]
            run_all([(f"train {mode} to {minutes:g} CPU-minutes", train_command(plan, mode, minutes, finish=last), log,
                      partial(progress_line, plan.run_dir(mode), minutes))], 1, tag="ranking")
            run_all([(f"gate {mode} at {minutes:g} CPU-minutes", internal(plan, "gate", f"{minutes:g}"),
                      plan.work / "logs" / "gate.log")], 1, tag="ranking")
        gates = [g for g in read_gates(plan) if g["budget_minutes"] <= minutes]  # those up to this point
        score = gates[-1]["from_chunk"]["0"]["balanced_accuracy"]
        print(f"[ranking]   gate at {minutes:g} CPU-minutes: balanced accuracy {score:.2f} (goal {plan.gate_min:g})",
              file=sys.stderr, flush=True)
        if gate_verdict(plan, gates) == "stop":
            write_report(plan)
            raise GateStop(f"the early gate: {mode}'s lift judge on replays of held-out training rollouts reached "
                           f"{max(g['from_chunk']['0']['balanced_accuracy'] for g in gates):.2f} balanced accuracy by "
                           f"{minutes:g} CPU-minutes, below {plan.gate_min:g}; the benchmark stops here "
                           f"(docs/ranking.md, \"The early gate\"; the gates: {plan.docs / 'README.md'})")


def stage_train(plan: RankingPlan) -> None:
    training_side(plan)  # so that `--stages train` alone trains the world models while the policies still train
    # a policy-blind mode (none: the harness check, none_minutes) trains here even for the GPU preset
    on_cpu = [m for m in plan.modes if m not in plan.compared_modes] if plan.on_gpu else list(plan.modes)
    gated = not plan.on_gpu and plan.gate_every is not None and GATED_MODE in plan.modes
    if gated and not (plan.run_dir(GATED_MODE) / "DONE.json").is_file():
        train_gated(plan)  # first, alone: the other modes train only once it has passed
    commands = [(f"train {mode}", train_command(plan, mode), plan.work / "logs" / f"train_{slug(mode)}.log",
                 partial(progress_line, plan.run_dir(mode), plan.cpu_budget(mode)))
                for mode in on_cpu if not (plan.run_dir(mode) / "DONE.json").is_file()]
    run_all(commands, plan.jobs, tag="ranking")
    if plan.on_gpu:
        train_on_gpu(plan)
