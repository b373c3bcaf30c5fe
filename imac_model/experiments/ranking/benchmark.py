"""Policy ranking in simulation (``make ranking``, ``imac-model ranking``): does the world model
rank policies the way MuJoCo does?

Stages, each cached under ``--work`` and resumed where it stopped, each timed (wall and CPU of
this process and its children):

1. ``simulate``: every policy in MuJoCo from the evaluation starts (``imac-model evaluate
   simulator``), and the world model's training rollouts (a mix of policies, other starts);
2. ``build``: both as LeRobot datasets with ``imac build`` (their success labels included);
3. ``decode``: the training chunks, decoded once;
4. ``train``: one world model per conditioning mode, the same CPU budget each;
5. ``judges``: the learned classifier, and both judges' accuracy on the real evaluation episodes;
6. ``evaluate``: every policy closed loop in every world model from the same starts and seeds
   (``none`` once per start, after checking its frames are bit-identical across policies), the
   recorded actions replayed for the judges' accuracy on generated frames, action sensitivity;
7. ``report``: ``docs/ranking/``.

``docs/ranking.md`` explains the protocol; the report holds the figures."""

from __future__ import annotations

from pathlib import Path

from imac_model.experiments.ranking.datasets import stage_build, stage_decode
from imac_model.experiments.ranking.evaluation import evaluated_policies, policy_dir
from imac_model.experiments.ranking.freeze import freeze_models
from imac_model.experiments.ranking.gate import read_gates
from imac_model.experiments.ranking.gpu import stage_pack
from imac_model.experiments.ranking.plan import RankingPlan, internal, slug
from imac_model.experiments.ranking.report import write_report
from imac_model.experiments.ranking.simulate import stage_simulate
from imac_model.experiments.ranking.training import stage_train
from imac_model.experiments.stages import run_all
from imac_model.models.checkpoint import list_checkpoints

# --------------------------------------------------------------------------- 5-6. judges, evaluate


def stage_judges(plan: RankingPlan) -> None:
    if (plan.work / "judges" / "real.json").is_file():
        return
    run_all([("judges", internal(plan, "judges"), plan.work / "logs" / "judges.log")], 1, tag="ranking")


def _gated_at_the_end(plan: RankingPlan, mode: str) -> bool:
    """Whether a gate of ``mode`` measured its last checkpoint (the same replays, seeds and weights give
    the same figures, so it is not measured twice)."""
    last = list_checkpoints(plan.run_dir(mode))
    return bool(last) and any(g.get("checkpoint") == last[-1].name for g in read_gates(plan, mode))


def stage_evaluate(plan: RankingPlan) -> None:
    freeze_models(plan)  # every mode evaluated as it ships

    def log(mode: str, what: str) -> Path:
        return plan.work / "logs" / f"evaluate_{slug(mode.replace('+', '_'))}{what}.log"

    # the gate of every compared mode at the end of its training, beside motion+contact's hourly ones
    gates = [(f"gate {mode}", internal(plan, "gate", f"{plan.budget_minutes:g}", mode), log(mode, "_gate"))
             for mode in plan.compared_modes if not _gated_at_the_end(plan, mode)]
    run_all(gates, plan.jobs, tag="ranking")
    # each mode's replays and each policy's closed loop in a process of its own, the longest first, so that the cores
    # stay busy to the end (one process per mode left one idle while motion+contact's ran on); then each mode's
    # outcomes from them, with the none check and the action sensitivity
    modes = [m for m in plan.modes if not (plan.wm_dir(m) / "outcomes.json").is_file()]

    replaying = [(f"replays {m}", internal(plan, "replays", m), log(m, "_replays")) for m in modes
                 if m in plan.compared_modes and not (plan.wm_dir(m) / "replays.json").is_file()]
    closed_loops = [(f"evaluate {m} {slug(p)}", internal(plan, "evaluate", m, p), log(m, f"_{slug(p)}"))
                    for m in modes for p in evaluated_policies(plan, m)
                    if not (policy_dir(plan, m, p) / "closed_loop.json").is_file()]
    run_all(replaying + closed_loops, plan.jobs, tag="ranking")
    run_all([(f"evaluate {m}", internal(plan, "evaluate", m), log(m, "")) for m in modes], plan.jobs, tag="ranking")


def stage_report(plan: RankingPlan) -> None:
    write_report(plan)


STAGE_FUNCTIONS = {"simulate": stage_simulate, "build": stage_build, "decode": stage_decode, "pack": stage_pack,
                   "train": stage_train,
                   "judges": stage_judges, "evaluate": stage_evaluate, "report": stage_report}
