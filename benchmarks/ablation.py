"""The ranking world model's ablations (:mod:`imac_model.experiments.ranking.ablations`, one table),
measured on a work directory where the arm and the run it changes are trained (the GPU preset's
``gpu_ablations``, imported with ``--import-gpu``; or ``python -m benchmarks.cpu_ablation``).

Each run is measured by the early gate (its held-out training rollouts replayed, balanced accuracy
of the lift judge from every chunk; measured here if missing) and on the replays of the evaluation
episodes (the lift judge against MuJoCo, the RGB error of each chunk over all pixels and over the
pixels that move in the recording, the generated depth's validity)::

    python -m benchmarks.ablation focus --work runs/ranking_gpu --json benchmarks/results/focus_ablation.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from imac_model.experiments.ranking.ablations import ABLATIONS, ablation
from imac_model.experiments.ranking.evaluation import replays
from imac_model.experiments.ranking.gate import measure_gate, read_gates
from imac_model.experiments.ranking.plan import GATED_MODE, RankingPlan
from imac_model.models.checkpoint import read_spec, resolve_checkpoint


def summary(plan: RankingPlan, run: str) -> dict:
    trained = json.loads((plan.work / "runs" / run / "DONE.json").read_text())  # the log's last row
    spec = read_spec(resolve_checkpoint(plan.work / "runs" / run))
    gates = read_gates(plan, run) or [measure_gate(plan, trained.get("wall_s", 0) / 60, run)]
    gate = replays(plan, GATED_MODE, None if plan.run_dir(GATED_MODE).name == run else run)[str(plan.steps)]
    return {"focus_weight": spec.flow.focus_weight, "reference_noise": spec.flow.reference_noise,
            "first_frame": spec.conditioning.first_frame, "scene_warp": spec.conditioning.scene_warp,
            "rollout": "phase" in trained, "steps": trained["step"],
            "gate_balanced_accuracy_from_chunk": {k: v["balanced_accuracy"] for k, v in gates[-1]["from_chunk"].items()},
            "lift_judge_accuracy": gate["accuracy"]["lift_geometry"],
            "mse_per_chunk": gate["mse_per_chunk"], "mse_moving_per_chunk": gate.get("mse_moving_per_chunk"),
            "mse_per_chunk_by_view": gate["mse_per_chunk_by_view"],
            "depth_valid_per_chunk": gate["depth_valid_per_chunk"], "replays": len(gate["rows"]),
            "seeds": gate.get("seeds", 1)}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("ablation", choices=sorted(ABLATIONS))
    p.add_argument("--work", default="runs/ranking_gpu", help="the GPU preset's work directory, runs imported")
    p.add_argument("--json", help="write the figures here")
    args = p.parse_args(argv)
    plan = RankingPlan.load(Path(args.work) / "plan.json")
    arm = ablation(args.ablation, plan.chunks)
    result = {"arm": summary(plan, arm.arm), "baseline": summary(plan, arm.baseline)}
    print(f"{args.ablation}: {arm.why} ({arm.arm}: {arm.changes}, against {arm.baseline})")
    for name, r in result.items():
        gate = " ".join(f"{x:.2f}" for x in r["gate_balanced_accuracy_from_chunk"].values())
        fmt = " ".join(f"{x:.4f}" for x in r["mse_moving_per_chunk"] or [])
        print(f"{name:10s} focus {r['focus_weight']}, rollout {r['rollout']}: {r['steps']} steps; gate from "
              f"chunk 1.. {gate}; lift judge {r['lift_judge_accuracy']:.2f} on {r['replays']} replays; moving-pixel "
              f"RGB MSE per chunk {fmt}")
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
