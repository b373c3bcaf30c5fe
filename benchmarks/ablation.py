"""The ranking world model's ablations: two runs trained on the same pack, for the same GPU time, in
the same call of ``scripts/gpu_ranking.sh``, one with a design choice and one without:

* ``focus``: the loss weighted on what moves (``motion_contact``) against a uniform loss
  (``motion_contact_uniform``, ``focus_weight 0``; ``ABLATION=1``);
* ``rollout``: training-time rollout (``motion_contact``, ``ROLLOUT=R``) against none
  (``motion_contact_no_rollout``; ``ABLATION=rollout``);
* ``first-frame``: the episode's first frame as memory (``motion_contact_first_frame``,
  ``conditioning.first_frame``) against none (``motion_contact``; ``ABLATION=first-frame``);
* ``scene-warp``: the scene-warp stream (``motion_contact_scene_warp``, ``conditioning.scene_warp``) against
  none (``motion_contact``; ``ABLATION=scene-warp``);
* ``contact``: a rolled-out chunk's contact images painted from its own reference (``motion_contact_rebuilt``,
  ``--rebuild-contact``) against the recorded ones (``motion_contact``; ``ABLATION=contact``).

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

from imac_model.experiments.ranking.evaluation import replays
from imac_model.experiments.ranking.gate import measure_gate, read_gates
from imac_model.experiments.ranking.plan import RankingPlan

ABLATIONS = {"focus": {"focus": "motion_contact", "uniform": "motion_contact_uniform"},
             "rollout": {"rollout": "motion_contact", "no_rollout": "motion_contact_no_rollout"},
             "first-frame": {"first_frame": "motion_contact_first_frame", "without": "motion_contact"},
             "scene-warp": {"scene_warp": "motion_contact_scene_warp", "without": "motion_contact"},
             "contact": {"rebuilt": "motion_contact_rebuilt", "recorded": "motion_contact"}}


def summary(plan: RankingPlan, run: str) -> dict:
    trained = json.loads((plan.work / "runs" / run / "DONE.json").read_text())
    gates = read_gates(plan, run) or [measure_gate(plan, trained.get("train_s", 0) / 60, run)]
    gate = replays(plan, "motion+contact", None if plan.run_dir("motion+contact").name == run else run)[str(plan.steps)]
    return {"focus_weight": trained.get("focus_weight"), "rollout_chunks": trained.get("rollout_chunks", 1),
            "first_frame": trained.get("first_frame", False), "scene_warp": trained.get("scene_warp", False),
            "rollout_reference_steps": trained.get("rollout_reference_steps", 0),
            "rebuild_contact": trained.get("rebuild_contact", False),
            "steps": trained["steps"], "samples": trained["samples"], "device": trained.get("device"),
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
    result = {name: summary(plan, run) for name, run in ABLATIONS[args.ablation].items()}
    for name, r in result.items():
        gate = " ".join(f"{x:.2f}" for x in r["gate_balanced_accuracy_from_chunk"].values())
        fmt = " ".join(f"{x:.4f}" for x in r["mse_moving_per_chunk"] or [])
        print(f"{name:10s} focus {r['focus_weight']}, rollout {r['rollout_chunks']}: {r['steps']} steps; gate from "
              f"chunk 1.. {gate}; lift judge {r['lift_judge_accuracy']:.2f} on {r['replays']} replays; moving-pixel "
              f"RGB MSE per chunk {fmt}")
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
