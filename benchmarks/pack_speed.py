"""Chunks per second of the trainer on a tensor pack, eager against ``torch.compile`` (the U-Net's
trunk, ``train.compile``), alone on one device at a runs file's settings. Each variant trains one run
of the file for a short wall-clock budget (``train.max_minutes``); the figure is its rate after the
first logged row, which holds the compilation::

    python -m benchmarks.pack_speed runs/ranking_gpu/gpu/runs.yaml --run motion_contact --json speed.json
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

from imac_model.training.runs import RunsFile
from imac_model.training.train import train

VARIANTS = ("eager", "compiled")


def measure(runs: RunsFile, run: str, *, seconds: float, batch_size: int | None = None,
            variants: tuple[str, ...] = VARIANTS) -> dict:
    """Each variant's steps and its chunks per second after its first logged row."""
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name in variants:
            config = runs.config(run, Path(tmp) / name)
            changes = {"train.compile": name == "compiled", "train.max_minutes": seconds / 60.0,
                       "train.max_cpu_minutes": None, "train.log_every": 5, "train.eval_every": 10 ** 9}
            if batch_size:
                changes["train.batch_size"] = batch_size
            config = config.replace(**changes)
            log = [r for r in train(config, progress=False).log if "loss" in r]
            later = log[1:] or log
            chunks = config.train.batch_size * sum(r["steps_per_s"] for r in later) / max(len(later), 1)
            rows[name] = {"steps": log[-1]["step"] if log else 0, "chunks_per_s_after_first_row": round(chunks, 1),
                          "compiled": bool(log and log[-1].get("compiled"))}
            print(json.dumps({name: rows[name]}), flush=True)
    result = {"run": run, "variants": rows}
    if set(VARIANTS) <= set(rows):
        result["speedup"] = round(rows["compiled"]["chunks_per_s_after_first_row"]
                                  / max(rows["eager"]["chunks_per_s_after_first_row"], 1e-9), 2)
    return result


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.pack_speed", description=__doc__.split("\n\n")[0])
    p.add_argument("runs_file", help="a runs file beside its pack (imac-model ranking --stages pack writes one)")
    p.add_argument("--run", default="motion_contact")
    p.add_argument("--seconds", type=float, default=40.0, help="wall seconds per variant, compilation included")
    p.add_argument("--batch-size", type=int, help="instead of the runs file's")
    p.add_argument("--variants", nargs="+", choices=VARIANTS, default=list(VARIANTS))
    p.add_argument("--json", help="write the figures here")
    args = p.parse_args(argv)
    result = measure(RunsFile.load(args.runs_file), args.run, seconds=args.seconds, batch_size=args.batch_size,
                     variants=tuple(args.variants))
    print(json.dumps(result))
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
