"""What a training-time rollout hands the next chunk: the cube in the one-step clean estimate's last
frame, by flow time, against the sampler's last frame and the recording.

Training-time rollout (:func:`imac_model.pipelines.rollout.rollout_loss`) starts chunk r > 1 from
the last frame of chunk r-1's one-step estimate, at the flow time that chunk was trained at
(``tau ~ U(0, 1)``; 0 is noise, 1 the data). This measures, on a run's held-out chunks from the
GPU preset's pack (torch alone), how much of the recorded cube each view of that frame keeps::

    python -m benchmarks.rollout_reference motion_contact --work runs/ranking_gpu2 \\
        --json benchmarks/results/rollout_reference.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from imac_model.data.batch import unit_frames
from imac_model.data.pack import Pack
from imac_model.experiments.ranking.gate import cube_in_view
from imac_model.experiments.ranking.plan import RankingPlan
from imac_model.models.checkpoint import load_world_model
from imac_model.pipelines.rollout import last_frame

TAUS = (0.1, 0.3, 0.5, 0.7, 0.9)
KEPT = 0.5  # a view keeps the cube when it shows at least this share of the recorded cube's red pixels


def _cube_kept(frames: torch.Tensor, recorded: torch.Tensor, spec) -> dict[str, dict[str, float]]:
    """Per view: the share of chunks whose frame keeps the recorded cube, and the median centroid offset (px)."""
    result = {}
    for view in spec.views:
        got, want = cube_in_view(frames, spec, view), cube_in_view(recorded, spec, view)
        shown = [(g, w) for g, w in zip(got, want) if w[0] > 0]
        kept = [g[0] >= KEPT * w[0] for g, w in shown]
        offsets = [float(np.hypot(g[1] - w[1], g[2] - w[2])) for g, w in shown if g[0] > 0]
        result[view] = {"kept": round(float(np.mean(kept)), 3) if kept else None,
                        "offset_px": round(float(np.median(offsets)), 2) if offsets else None, "chunks": len(shown)}
    return result


@torch.no_grad()
def measure(plan: RankingPlan, run: str, seed: int = 0) -> dict:
    torch.set_num_threads(1)
    pack = Pack(plan.work / "gpu" / "pack.npz")
    model, spec = load_world_model(plan.work / "runs" / run, weights="ema")
    model = model.float().eval()
    streams = spec.conditioning.streams
    # the held-out chunks a rollout goes on from: every one but its episode's last
    episode = pack.tensors["episode_index"]
    index = torch.tensor([int(i) for i in pack.heldout if int(i) + 1 < len(episode) and episode[i + 1] == episode[i]])
    batch = pack.batch(index, streams)
    recorded = unit_frames(batch.future[:, -1])
    rows = {}
    for tau in TAUS:
        g = torch.Generator().manual_seed(seed)
        out = model(batch, generator=g, tau=torch.full((len(index),), tau), streams=streams or None)
        rows[f"{tau:g}"] = _cube_kept(last_frame(model, out), recorded, spec)
        print(json.dumps({"tau": tau, **rows[f"{tau:g}"]}), flush=True)
    sampled = model.sample(batch, generator=torch.Generator().manual_seed(seed), steps=plan.steps).frames[:, -1]
    rows["sampler"] = _cube_kept(unit_frames(sampled), recorded, spec)
    print(json.dumps({"sampler": rows["sampler"]}), flush=True)
    return {"work": plan.work.name, "run": run, "chunks": len(index), "taus": rows, "sampler_steps": plan.steps}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.rollout_reference", description=__doc__.split("\n\n")[0])
    p.add_argument("run", help="a trained run of the work directory (runs/<run>)")
    p.add_argument("--work", default="runs/ranking_gpu2", help="the ranking benchmark's work directory")
    p.add_argument("--json", help="append the figures to this file")
    args = p.parse_args(argv)
    result = measure(RankingPlan.load(Path(args.work) / "plan.json"), args.run)
    if args.json:
        path = Path(args.json)
        rows = json.loads(path.read_text()) if path.is_file() else []
        path.write_text(json.dumps([*rows, result], indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
