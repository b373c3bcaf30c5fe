"""Where the scene warp puts the cube, against where the recording has it: an oracle of the geometry the first
chunks' controls are made from (docs/ranking.md, "Starts, seeds and data").

    python -m benchmarks.warp_oracle --work runs/side_across [--json out.json]

The scene warp reprojects a chunk's reference frame into every view at each future step; for a still scene it is
exact up to the splat. For the first and second chunk of every training rollout in the work directory's tensor
pack, each view and future step: the median and 90th percentile of the distance (px, at the model's view size)
between the cube's red centroid in the warp and in the recorded frame, over the rollouts where both show it; and
the cube's bottom row in the workspace view at t = 0 and t = 1 (a cube that falls at the start moves it)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from imac_model.data.pack import Pack
from imac_model.experiments.ranking.gate import cube_in_view
from imac_model.experiments.ranking.perception import RED_THRESHOLD, redness
from imac_model.experiments.ranking.plan import RankingPlan
from imac_model.experiments.ranking.policies import WORKSPACE

STEPS = (1, 4, 8)  # the future steps reported


def _bottom_row(rgb: torch.Tensor) -> float:
    rows = torch.nonzero(redness(rgb) > RED_THRESHOLD)[:, 0]
    return float(rows.max()) if len(rows) else float("nan")


def measure(pack: Pack) -> dict:
    spec, t = pack.spec, pack.tensors
    first = torch.nonzero(pack.first_chunk == torch.arange(len(pack.first_chunk))).flatten()
    out = {"rollouts": len(first), "chunks": {}}
    for k in (0, 1):
        batch = pack.batch(first + k, ("scene_warp",))
        table = {}
        for view in spec.views:
            rows = {}
            for step in STEPS:
                d = []
                for i in range(len(first)):
                    (rec,) = cube_in_view(batch.future[i, step - 1:step], spec, view)
                    (warp,) = cube_in_view(batch.controls["scene_warp"][i, step - 1:step], spec, view)
                    if rec[0] and warp[0]:
                        d.append(float(np.hypot(rec[1] - warp[1], rec[2] - warp[2])))
                rows[str(step)] = ({"n": len(d), "median_px": round(float(np.median(d)), 2),
                                    "p90_px": round(float(np.percentile(d, 90)), 2)} if d else {"n": 0})
            table[view] = rows
        out["chunks"][str(k + 1)] = table
    v, h, w = spec.views.index(WORKSPACE), spec.view_height, spec.view_width
    ref = t["reference"][first].float() / 255.0
    fut = t["future"][first, 0].float() / 255.0
    out["workspace_bottom_row"] = {
        "t0": round(float(np.nanmedian([_bottom_row(x[:, :h, v * w:(v + 1) * w]) for x in ref])), 2),
        "t1": round(float(np.nanmedian([_bottom_row(x[:, :h, v * w:(v + 1) * w]) for x in fut])), 2)}
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.warp_oracle", description=__doc__.splitlines()[0])
    p.add_argument("--work", required=True, help="a ranking work directory with its tensor pack (--stages pack)")
    p.add_argument("--json", help="also write the figures here")
    args = p.parse_args(argv)
    plan = RankingPlan.load(Path(args.work) / "plan.json")
    result = {"work": args.work, "settle_s": plan.settle_s, **measure(Pack(plan.pack))}
    print(f"{args.work} (settle_s {plan.settle_s:g}): {result['rollouts']} rollouts; the cube's bottom row in the "
          f"workspace view {result['workspace_bottom_row']['t0']} at t=0, {result['workspace_bottom_row']['t1']} at t=1")
    print("| chunk | view | " + " | ".join(f"step {s}: median / p90 px" for s in STEPS) + " |")
    print("|---|---|" + "---|" * len(STEPS))
    for k, table in result["chunks"].items():
        for view, rows in table.items():
            cells = [f"{r['median_px']} / {r['p90_px']} ({r['n']})" if r["n"] else "no cube" for r in rows.values()]
            print(f"| {k} | {view} | " + " | ".join(cells) + " |")
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
