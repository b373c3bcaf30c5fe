"""``imac-model train``: train the world model on an imac dataset."""

from __future__ import annotations

import argparse

import yaml

from imac_data.console import run_command
from imac_data.errors import InputError
from imac_model.config import load_run_config
from imac_model.training.train import train


def overrides_of(args: argparse.Namespace) -> dict:
    """The run-config fields the command line sets: its own flags and every ``--set FIELD=VALUE``."""
    overrides = {}
    for key, value in (("data.dataset", args.dataset), ("data.root", args.root),
                       ("conditioning.mode", args.mode), ("train.output_dir", args.output_dir)):
        if value is not None:
            overrides[key] = value
    return {**overrides, **set_overrides(args.set)}


def set_overrides(items) -> dict:
    """``--set FIELD=VALUE`` items as run-config overrides, each value read as YAML."""
    overrides = {}
    for item in items or ():
        if "=" not in item:
            raise InputError(f"--set {item!r}: expected FIELD=VALUE")
        key, value = item.split("=", 1)
        overrides[key.strip()] = yaml.safe_load(value)
    return overrides


def run(args: argparse.Namespace) -> int:
    def body() -> int:
        result = train(load_run_config(args.config, overrides_of(args)), resume=args.resume,
                       progress=not args.no_progress)
        if not result.main:  # another process of a distributed run: rank 0 reports
            return 0
        last = [r for r in result.log if "heldout_loss" in r]
        summary = f"trained to step {result.step} ({result.stopped}); checkpoint {result.checkpoint}"
        if len(last) >= 2:
            summary += f"; held-out flow loss {last[0]['heldout_loss']:.4f} -> {last[-1]['heldout_loss']:.4f}"
        print(summary)
        return 0

    return run_command(body)
