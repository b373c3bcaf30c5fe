"""Does the loss that looks where things move help? The loss-weighting ablation of the ranking's
world model: ``motion+contact`` trained with ``flow.focus_weight`` (the benchmark's setting) and
with a uniform loss (``motion_contact_uniform``, ``focus_weight 0``), on the same pack, for the
same GPU time, in the same call (``ABLATION=1 bash scripts/gpu_ranking.sh``).

Both are measured on the gate's replays (the recorded actions of real evaluation episodes, half
successes; docs/ranking.md): the lift judge against MuJoCo, the RGB error of each chunk over all
pixels and over the pixels that move in the recording, and the generated depth's validity::

    python -m benchmarks.focus_ablation --work runs/ranking_gpu --json benchmarks/results/focus_ablation.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from imac_model.experiments.ranking.evaluation import replays
from imac_model.experiments.ranking.plan import RankingPlan

RUNS = {"focus": None, "uniform": "motion_contact_uniform"}  # None: the plan's motion+contact run


def summary(plan: RankingPlan, run: str | None) -> dict:
    run_dir = plan.run_dir("motion+contact") if run is None else plan.work / "runs" / run
    trained = json.loads((run_dir / "DONE.json").read_text())
    gate = replays(plan, "motion+contact", run)[str(plan.steps)]
    return {"focus_weight": trained.get("focus_weight"), "steps": trained["steps"], "samples": trained["samples"],
            "device": trained.get("device"), "lift_judge_accuracy": gate["accuracy"]["lift_geometry"],
            "mse_per_chunk": gate["mse_per_chunk"], "mse_moving_per_chunk": gate.get("mse_moving_per_chunk"),
            "mse_per_chunk_by_view": gate["mse_per_chunk_by_view"],
            "depth_valid_per_chunk": gate["depth_valid_per_chunk"], "replays": len(gate["rows"])}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--work", default="runs/ranking_gpu", help="the GPU preset's work directory, runs imported")
    p.add_argument("--json", help="write the figures here")
    args = p.parse_args(argv)
    plan = RankingPlan.load(Path(args.work) / "plan.json")
    result = {name: summary(plan, run) for name, run in RUNS.items()}
    for name, r in result.items():
        fmt = " ".join(f"{x:.4f}" for x in r["mse_moving_per_chunk"] or [])
        print(f"{name:8s} focus {r['focus_weight']}: {r['steps']} steps, lift judge {r['lift_judge_accuracy']:.2f} "
              f"on {r['replays']} replays; moving-pixel RGB MSE per chunk {fmt}; all-pixel "
              + " ".join(f"{x:.4f}" for x in r["mse_per_chunk"]))
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
