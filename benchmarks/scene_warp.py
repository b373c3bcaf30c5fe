"""What the scene-warp stream tells the model, against MuJoCo's recorded frames.

For each chunk of the ranking benchmark's held-out training rollouts, the warp of the recorded
reference (:class:`imac_model.data.scene_warp.SceneWarp`, the stream a ``conditioning.scene_warp``
model gets) is compared with the recorded future frame at its steps 4 and 8:

* **the cube:** in each view, how often the recording shows it, whether the warp shows it too, and
  the distance (pixels at the model's view size) between their red centroids;
* **the scene:** the mean absolute RGB error on pixels that are scene in both (warped, and neither
  where the robot was nor where it goes), of the warp and of the reference left in place.

It also times the warp per chunk (one process, one thread)::

    python -m benchmarks.scene_warp --work runs/ranking_cpu --json benchmarks/results/scene_warp.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from imac_data.core.contact.clouds import dilate_mask
from imac_model.data import mosaic
from imac_model.data.chunks import ChunkDataset, open_metadata, split_episodes
from imac_model.data.scene_warp import SceneWarp
from imac_model.experiments.ranking.gate import cube_in_view
from imac_model.experiments.ranking.plan import TRAIN_REPO, RankingPlan
from imac_model.training.dataset_source import model_spec

STEPS = (4, 8)


def measure(plan: RankingPlan, chunks: int) -> dict:
    torch.set_num_threads(1)
    run = plan.run_config("motion+contact")
    meta = open_metadata(run.data)
    spec, layout = model_spec(run, meta)
    _, held = split_episodes(meta.total_episodes, run.data.held_out_episodes)
    ds = ChunkDataset(TRAIN_REPO, layout, root=run.data.root, episodes=held, cache="memory",
                      cache_dir=run.data.cache_dir)
    warp = SceneWarp.from_dataset(meta, run.data.root, spec.views, (spec.view_height, spec.view_width))
    V = len(spec.views)
    rows, seconds = [], []
    for e in held:
        for c, i in enumerate(ds.episode_chunks(e)[:chunks]):
            item = ds[i]
            reference = item["reference"][None].float() / 255
            t0 = time.process_time()
            images = warp.images(reference, item["state"][None], item["actions"][None])[0]  # (H, V, 3, h, w)
            seconds.append(time.process_time() - t0)
            q_future = warp.rig.rollout(item["state"][None], item["actions"][None])[0]
            robot = warp.rig.robot_views(torch.cat([item["state"][None], q_future]), resolution=warp.view_hw,
                                         gripper=False).mask
            recorded, _ = mosaic.split(item["future"].float() / 255, V)
            kept, _ = mosaic.split(reference, V)
            warped = mosaic.assemble(images, torch.zeros_like(images))
            for v, view in enumerate(spec.views):
                cube_w, cube_r = cube_in_view(warped, spec, view), cube_in_view(item["future"].float() / 255, spec, view)
                for s in STEPS:
                    g, r = cube_w[s - 1], cube_r[s - 1]
                    scene = (images[s - 1, v].amax(0) > 0) & ~dilate_mask(robot[0, v] | robot[s, v], 2)
                    err = lambda x: float((x - recorded[s - 1, v]).abs().mean(0)[scene].mean()) if scene.any() else None  # noqa: E731
                    rows.append({"episode": e, "chunk": c + 1, "view": view, "step": s, "recorded_px": r[0],
                                 "warp_px": g[0],
                                 "offset_px": (float(np.hypot(g[1] - r[1], g[2] - r[2])) if g[0] and r[0] else None),
                                 "scene_error_warp": err(images[s - 1, v]), "scene_error_kept": err(kept[0, v])})
    summary = []
    for view in spec.views:
        for c in range(1, chunks + 1):
            for s in STEPS:
                sel = [r for r in rows if r["view"] == view and r["chunk"] == c and r["step"] == s]
                off = [r["offset_px"] for r in sel if r["offset_px"] is not None]
                ew = [r["scene_error_warp"] for r in sel if r["scene_error_warp"] is not None]
                ek = [r["scene_error_kept"] for r in sel if r["scene_error_kept"] is not None]
                summary.append({"view": view, "chunk": c, "step": s, "n": len(sel),
                                "recorded_shows": sum(r["recorded_px"] > 0 for r in sel),
                                "warp_shows_too": len(off), "median_offset_px": float(np.median(off)) if off else None,
                                "scene_error_warp": float(np.mean(ew)) if ew else None,
                                "scene_error_kept": float(np.mean(ek)) if ek else None})
    return {"episodes": held, "view_hw": [spec.view_height, spec.view_width], "chunks": chunks,
            "seconds_per_chunk": float(np.mean(seconds)), "summary": summary, "rows": rows}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--work", default="runs/ranking_cpu", help="the ranking benchmark's work directory")
    p.add_argument("--chunks", type=int, default=4, help="chunks of each episode, from the first")
    p.add_argument("--json", help="write the figures here")
    args = p.parse_args(argv)
    result = measure(RankingPlan.load(Path(args.work) / "plan.json"), args.chunks)
    print(f"{len(result['episodes'])} held-out rollouts, views {result['view_hw'][0]}x{result['view_hw'][1]}; "
          f"warp {1000 * result['seconds_per_chunk']:.0f} CPU-ms per chunk")
    print(f"{'view':16s} chunk step  cube: recorded  warp too  offset px | scene error: warp  kept")
    for r in result["summary"]:
        fmt = lambda x, f: "-" if x is None else format(x, f)  # noqa: E731
        print(f"{r['view']:16s} {r['chunk']:5d} {r['step']:4d}  {r['recorded_shows']:8d}/{r['n']:<3d}"
              f"{r['warp_shows_too']:8d}  {fmt(r['median_offset_px'], '9.2f')} | "
              f"{fmt(r['scene_error_warp'], '17.3f')}  {fmt(r['scene_error_kept'], '.3f')}")
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
