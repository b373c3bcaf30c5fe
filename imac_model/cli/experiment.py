"""``imac-model experiment``: the small-scale comparison of ``docs/experiment`` (record, build,
decode, train five settings, evaluate, report), every stage cached and resumable."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from imac_data.console import run_command
from imac_data.errors import InputError
from imac_model.experiments.comparison import (
    SETTINGS,
    STAGES,
    Plan,
    decode_chunks,
    evaluate_setting,
    stage_build,
    stage_decode,
    stage_evaluate,
    stage_record,
    stage_report,
    stage_train,
)
from imac_model.experiments.stages import StageLog


def run(args: argparse.Namespace) -> int:
    return run_command(lambda: _experiment(args))


def _experiment(args: argparse.Namespace) -> int:
    plan = Plan(work=Path(args.work).resolve(), docs=Path(args.docs).resolve(), episodes=args.episodes,
                held_out=args.held_out, cpu_minutes=args.cpu_minutes, jobs=args.jobs, seed=args.seed,
                steps=args.steps, warmup_epochs=args.warmup_epochs)
    if not 0 < plan.held_out < plan.episodes:
        raise InputError(f"--held-out {plan.held_out}: must be between 1 and --episodes - 1")
    if args.internal == "decode":
        decode_chunks(plan)
        return 0
    if args.internal == "evaluate":
        evaluate_setting(plan, next(s for s in SETTINGS if s.slug == args.setting))
        return 0
    stages = [x.strip() for x in args.stages.split(",") if x.strip()]
    bad = [x for x in stages if x not in STAGES]
    if bad:
        raise InputError(f"--stages: unknown {bad}; choose from {list(STAGES)}")
    plan.work.mkdir(parents=True, exist_ok=True)
    (plan.work / "plan.json").write_text(json.dumps({**{k: str(v) for k, v in vars(plan).items()},
                                                     "argv": sys.argv}, indent=1))
    log = StageLog(plan.work / "stages.json")
    fns = {"record": stage_record, "build": stage_build, "decode": stage_decode, "train": stage_train,
           "evaluate": stage_evaluate, "report": stage_report}
    try:
        for stage in STAGES:
            if stage in stages:
                log.run(stage, lambda f=fns[stage]: f(plan))
    except RuntimeError as e:  # a stage's subprocess failed; its own output says why
        print(f"error: {e}", file=sys.stderr)
        return 1
    print(f"report: {plan.docs / 'README.md'}")
    return 0

