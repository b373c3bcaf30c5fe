"""Samples per second of the pack trainer, eager against ``torch.compile`` (the U-Net's trunk),
alone on one device at the GPU preset's settings. Each variant trains from the pack for a short
wall-clock budget through :func:`imac_model.training.pack.train_pack`; the figure is its rate
after the first step, which holds the compilation (``first_step_s``). ``scripts/gpu_ranking.sh``
runs it after its trainings (``SPEED=1``), when the compiler's caches are warm::

    python -m benchmarks.pack_speed --pack runs/ranking_gpu2/gpu/pack.npz --rollout-chunks 4 --json speed.json
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import torch

from imac_model.training.pack import Pack, fast_kernels, train_pack

VARIANTS = ("eager", "compiled")
# every variant's first step also sets up CUDA and cuDNN's autotuned convolutions: 7-19 s on an H100 (2026-11-27)
FIRST_STEP_ALLOWANCE_S = 25.0


def measure(pack: Pack, mode: str, *, seconds: float, batch_size: int, rollout_chunks: int,
            variants: tuple[str, ...] = VARIANTS, compile_allowance_s: float = 30.0) -> dict:
    """Each variant's summary: its first step (set-up, and the compilation: ``compile_allowance_s``
    more) and then about ``seconds`` of steps, whose rate is the figure."""
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name in variants:
            compiled = name == "compiled"
            budget = seconds + FIRST_STEP_ALLOWANCE_S + (compile_allowance_s if compiled else 0.0)
            summary = train_pack(pack, mode, Path(tmp) / name, minutes=budget / 60.0, batch_size=batch_size,
                                 rollout_chunks=rollout_chunks, compile=compiled, progress=lambda _: None)
            rows[name] = {k: summary[k] for k in ("compiled", "first_step_s", "steps", "samples",
                                                  "samples_per_s_after_first_step", "device", "torch")}
            print(json.dumps({"batch_size": batch_size, name: rows[name]}), flush=True)
    result = {"mode": mode, "batch_size": batch_size, "rollout_chunks": rollout_chunks, "variants": rows}
    if set(VARIANTS) <= set(rows):
        result["speedup"] = round(rows["compiled"]["samples_per_s_after_first_step"] / max(
            rows["eager"]["samples_per_s_after_first_step"], 1e-9), 2)
    return result


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.pack_speed", description=__doc__.split("\n\n")[0])
    p.add_argument("--pack", required=True)
    p.add_argument("--mode", default="motion+contact")
    p.add_argument("--seconds", type=float, default=12.0, help="steady-state seconds per variant")
    p.add_argument("--batch-size", type=int, nargs="+", default=[128], help="one measurement per batch size")
    p.add_argument("--variants", nargs="+", choices=VARIANTS, default=list(VARIANTS))
    p.add_argument("--compile-allowance", type=float, default=30.0,
                   help="seconds added to a compiled variant's budget for its compilation (warm caches: 30)")
    p.add_argument("--rollout-chunks", type=int, default=1)
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--json", help="write the figures here")
    args = p.parse_args(argv)
    fast_kernels()
    pack = Pack(args.pack, args.device)
    results = [measure(pack, args.mode, seconds=args.seconds, batch_size=b, rollout_chunks=args.rollout_chunks,
                       variants=tuple(args.variants), compile_allowance_s=args.compile_allowance)
               for b in args.batch_size]
    result = results[0] if len(results) == 1 else results
    print(json.dumps(result))
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
