"""``imac-model ranking``: the policy-ranking benchmark of ``docs/ranking.md`` (simulate, build,
decode, train, judges, evaluate, report), every stage cached and resumable."""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

from imac_data.console import run_command
from imac_data.dataset.output import output_lock
from imac_data.errors import InputError
from imac_model.cli.train import set_overrides
from imac_model.experiments.ranking.benchmark import STAGE_FUNCTIONS
from imac_model.experiments.ranking.datasets import decode_chunks
from imac_model.experiments.ranking.evaluation import evaluate_mode, evaluate_policy, replays, run_judges
from imac_model.experiments.ranking.gate import measure_gate
from imac_model.experiments.ranking.gpu import export_runs, export_training_pack, import_gpu_runs
from imac_model.experiments.ranking.plan import STAGES, RankingPlan, checkpoints_plan, gpu_plan, plan_path, toy_plan
from imac_model.experiments.ranking.report import rewrite_report
from imac_model.experiments.ranking.shipped import rerun_plan, run_from_models
from imac_model.experiments.ranking.simulate import simulate_training_part
from imac_model.experiments.ranking.status import status
from imac_model.experiments.ranking.training import GateStop
from imac_model.experiments.stages import StageLog

EXIT_GATE_STOP = 4  # the early gate stopped the benchmark (docs/ranking.md); 3 is an environment fault


def run(args: argparse.Namespace) -> int:
    return run_command(lambda: _ranking(args))


def _plan(args: argparse.Namespace) -> RankingPlan:
    work = Path(args.work).resolve()
    # without --docs, a work directory's report stays where its run put it
    saved = json.loads(plan_path(work).read_text())["docs"] if plan_path(work).is_file() else "docs/ranking"
    docs = Path(args.docs or saved).resolve()
    if args.toy and args.preset != "cpu":
        raise InputError(f"--toy and --preset {args.preset} are two sizes; choose one")
    plan = toy_plan(work, docs) if args.toy else gpu_plan(work, docs) if args.preset == "gpu" else \
        checkpoints_plan(work, docs) if args.preset == "checkpoints" else \
        RankingPlan(work=work, docs=docs)
    changes = {k: v for k, v in (("policies", tuple(args.policies or ()) or None), ("cpu_minutes", args.cpu_minutes),
                                 ("steps", args.steps), ("jobs", args.jobs),
                                 ("training_offsets", args.training_offsets), ("settle_s", args.settle),
                                 ("training_policies", tuple(args.training_policies or ()) or None),
                                 ("training_policy_share", args.training_policy_share),
                                 ("views", tuple(args.views or ()) or None),
                                 ("modes", tuple(args.modes or ()) or None))
               if v is not None}
    if args.gpu_minutes is not None:  # trained on a GPU: no CPU-hourly early gate (gpu_plan's choice)
        changes.update(gpu_minutes=args.gpu_minutes, gate_every=None)
    if args.set:
        changes["overrides"] = {**plan.overrides, **set_overrides(args.set)}
    plan = dataclasses.replace(plan, **changes)
    for mode in plan.modes:  # a field or value the run config refuses, before any work
        plan.run_config(mode)
    return same_as_saved(plan)


def _rerun_plan(args: argparse.Namespace) -> RankingPlan:
    models, work = Path(args.from_models).resolve(), Path(args.work).resolve()
    docs = Path(args.docs).resolve() if args.docs else work / "report"
    if docs == models.parent:
        raise InputError(f"--docs {args.docs}: the report the models belong to is there; the rerun's goes elsewhere")
    given = [k for k in ("preset", "cpu_minutes", "gpu_minutes", "steps", "training_offsets", "training_policies",
                         "training_policy_share", "settle", "views", "stages", "modes", "set")
             if getattr(args, k) not in (None, "cpu")] + (["toy"] if args.toy else [])
    if given:
        raise InputError(f"--from-models runs the report's plan; {', '.join('--' + k.replace('_', '-') for k in given)} "
                         "would change it")
    plan = rerun_plan(models, work, docs, tuple(args.policies or ()), args.starts)
    return same_as_saved(dataclasses.replace(plan, jobs=args.jobs) if args.jobs else plan)


def same_as_saved(plan: RankingPlan) -> RankingPlan:
    """``plan``, refused when its work directory holds a run with other settings. Where the report goes
    (``docs``) is not a setting of the run: another ``--docs`` writes the same report there."""
    work = plan.work
    saved = plan_path(work)
    if saved.is_file():
        theirs = {**RankingPlan.load(saved).to_dict(), "docs": str(plan.docs)}
        if theirs != plan.to_dict():
            differ = [f"{k}: {theirs.get(k)!r} there, {v!r} here" for k, v in sorted(plan.to_dict().items())
                      if theirs.get(k) != v]
            raise InputError(f"{saved}: the work directory holds a run with other settings ({'; '.join(differ)}); "
                             "give the same settings (e.g. --settle 0, --training-offsets disc for older ones), "
                             "choose another --work, or delete it")
    return plan


def stages_to_run(given: str | None, plan: RankingPlan) -> list[str]:
    """``--stages`` as a list, checked; without it, every stage the plan's preset needs (the tensor
    pack only for the GPU preset, which trains from it)."""
    if given is None:
        return [s for s in STAGES if s != "pack" or plan.on_gpu]
    stages = [x.strip() for x in given.split(",") if x.strip()]
    bad = [x for x in stages if x not in STAGES]
    if bad or not stages:
        raise InputError(f"--stages: unknown {bad or given!r}; choose from {list(STAGES)}")
    return stages


def _ranking(args: argparse.Namespace) -> int:
    if args.internal:
        plan = RankingPlan.load(Path(args.plan))
        {"train-rollouts": lambda: simulate_training_part(plan, int(args.internal_args[0])),
         "decode": lambda: decode_chunks(plan), "pack": lambda: export_training_pack(plan), "judges": lambda: run_judges(plan),
         "evaluate": lambda: (evaluate_policy(plan, *args.internal_args[:2]) if len(args.internal_args) > 1
                              else evaluate_mode(plan, args.internal_args[0])),
         "replays": lambda: replays(plan, *args.internal_args[:2]),
         "gate": lambda: measure_gate(plan, float(args.internal_args[0]), *args.internal_args[1:2])}[args.internal]()
        return 0
    if args.plan:  # hidden: the stages pass it to the processes they start; a user's would be ignored
        raise InputError(f"--plan {args.plan}: only the benchmark's own processes (--internal) read a plan; "
                         "give --work DIR (its plan.json is read and checked) and the settings to run")
    if args.runs and not args.export_runs:
        raise InputError("--runs names the runs --export-runs writes; give --export-runs DIR")
    if args.status:
        saved = plan_path(Path(args.work).resolve())
        if not saved.is_file():
            raise InputError(f"{saved.parent}: no benchmark run there (no plan.json); start one with imac-model ranking "
                             f"--work {args.work}")
        print(status(RankingPlan.load(saved)))
        return 0
    if args.rewrite_report:
        print(f"rewrote {rewrite_report(Path(args.docs))}")
        return 0
    if args.starts is not None and not args.from_models:
        raise InputError("--starts picks starts of the report that --from-models reruns; give --from-models")
    if args.from_models:
        plan = _rerun_plan(args)
        plan.check_policies("ranked")  # the report's training policies trained its models, not needed here
        plan.work.mkdir(parents=True, exist_ok=True)
        with output_lock(plan.work, who="imac-model ranking", hint="wait for it to finish, or stop it"):
            plan.save()
            StageLog(plan.work / "stages.json", tag="ranking").run(
                "from-models", lambda: run_from_models(plan, Path(args.from_models)))
        print(f"report: {plan.docs / 'README.md'}")
        return 0
    plan = _plan(args)
    stages = stages_to_run(args.stages, plan)
    if args.export_runs:  # reads finished runs only, so it takes no lock: a run may go on training there
        for path in export_runs(plan, Path(args.export_runs), args.runs):
            print(f"wrote {path} ({path.stat().st_size / 1e6:.1f} MB)")
        return 0
    plan.work.mkdir(parents=True, exist_ok=True)
    # one run per work directory at a time: two would train (or import) the same checkpoints
    with output_lock(plan.work, who="imac-model ranking", hint="wait for it to finish, or stop it"):
        if args.import_gpu:
            print(f"imported {import_gpu_runs(plan, Path(args.import_gpu))} into {plan.work / 'runs'}")
            plan.save()  # so that --status reads it
            return 0
        return _run_stages(plan, stages)


def _run_stages(plan: RankingPlan, stages: list[str]) -> int:
    # the stages that run policies: pack and train simulate the training rollouts (the training policies' among
    # them) and nothing else, so they may start while the ranked checkpoints still train
    ranked = bool({"simulate", "build", "evaluate"} & set(stages))
    if ranked or ({"pack", "train"} & set(stages) and plan.training_policies):
        plan.check_policies("all" if ranked else "training")
    plan.save()
    log = StageLog(plan.work / "stages.json", tag="ranking")
    try:
        for stage in STAGES:
            if stage in stages:
                log.run(stage, lambda f=STAGE_FUNCTIONS[stage]: f(plan))
    except GateStop as e:  # a result, not a failure of the run: the report holds it
        print(f"stopped: {e}", file=sys.stderr)
        return EXIT_GATE_STOP
    except RuntimeError as e:  # a stage's subprocess failed; its log says why
        print(f"error: {e}", file=sys.stderr)
        return 1
    print(f"report: {plan.docs / 'README.md'}")
    return 0
