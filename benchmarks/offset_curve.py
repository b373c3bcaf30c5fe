"""Success by grasp offset: the ranking benchmark's lift planner in MuJoCo, closed loop and open loop, grasping
``offset`` cm off the cube across the fingers (world +y), from the evaluation starts the benchmark uses, with the
plan's protocol (the workspace view alone at 48x64, 4 chunks, the box settled first). Where the rates lie strictly
between 0.2 and 0.8 is where graded scripted policies must grasp (docs/ranking.md, "Success by grasp offset")::

    python -m benchmarks.offset_curve --starts 50 --json benchmarks/results/offset_curve.json

Each policy kind runs in a process of its own (``--jobs``); each rollout is about a CPU-second."""

from __future__ import annotations

import argparse
import json
import multiprocessing
from pathlib import Path

import numpy as np

from imac_model.evaluate.simulator import SimRunConfig, SimRunner, run_policy
from imac_model.experiments.ranking.plan import EVAL_SEED0, RankingPlan
from imac_model.experiments.ranking.policies import LiftPolicy

KINDS = {"closed_loop": {}, "open_loop": {"relocalise": None}}


def curve(kind: str, offsets_cm: list[float], starts: int) -> dict:
    """MuJoCo's success rate of ``kind`` at each offset, over the first ``starts`` evaluation starts (group 0)."""
    plan = RankingPlan(work=Path("unused"), docs=Path("unused"))
    config = SimRunConfig(chunks=plan.chunks, view_height=plan.view_size[0], view_width=plan.view_size[1],
                          views=plan.views, settle_s=plan.settle_s)
    seeds = [EVAL_SEED0 + i for i in range(starts)]
    out = {}
    with SimRunner(config) as runner:
        for cm in offsets_cm:
            policy = LiftPolicy(f"{kind}_{cm:g}cm", offset=(0.0, cm / 100.0), **KINDS[kind])
            rows = run_policy(policy, seeds, runner=runner, progress=False)
            out[f"{cm:g}"] = float(np.mean([r["success"] for r in rows]))
            print(json.dumps({"kind": kind, "offset_cm": cm, "success": out[f"{cm:g}"], "starts": starts}), flush=True)
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.offset_curve", description=__doc__.split("\n\n")[0])
    p.add_argument("--starts", type=int, default=50, help="evaluation starts per offset")
    p.add_argument("--offsets", type=float, nargs="+", default=[0, 0.5, 1, 1.5, 2, 2.5, 3, 3.5, 4],
                   help="grasp offsets across the fingers, cm")
    p.add_argument("--kinds", nargs="+", choices=sorted(KINDS), default=sorted(KINDS))
    p.add_argument("--jobs", type=int, default=2)
    p.add_argument("--json", help="write the curve here")
    args = p.parse_args(argv)
    with multiprocessing.get_context("spawn").Pool(min(args.jobs, len(args.kinds))) as pool:
        curves = pool.starmap(curve, [(k, args.offsets, args.starts) for k in args.kinds])
    result = {"starts": args.starts, "protocol": "RankingPlan defaults: workspace view 48x64, 4 chunks, settle 0.3 s",
              "success": dict(zip(args.kinds, curves))}
    print("| offset cm | " + " | ".join(args.kinds) + " |")
    for cm in args.offsets:
        print(f"| {cm:g} | " + " | ".join(f"{result['success'][k][f'{cm:g}']:.2f}" for k in args.kinds) + " |")
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
