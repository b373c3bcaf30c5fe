"""``imac-model plan``: the memory and compute plan of a run config, on the meta device."""

from __future__ import annotations

import argparse
from pathlib import Path

from imac_data.console import run_command
from imac_model.cli.train import set_overrides
from imac_model.config import load_run_config
from imac_model.training.plan import format_plan, make_plan, plan_json


def run(args: argparse.Namespace) -> int:
    def body() -> int:
        plan = make_plan(load_run_config(args.config, set_overrides(args.set)), gpus=tuple(args.gpus),
                         gpu_gb=args.gpu_gb, reserve_gb=args.reserve_gb, micro_batch=args.micro_batch, views=args.views,
                         action_dim=args.action_dim)
        print(format_plan(plan, args.config))
        if args.json:
            Path(args.json).write_text(plan_json(plan) + "\n")
        return 0

    return run_command(body)
