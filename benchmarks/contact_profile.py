"""Where the contact stage's CPU goes: the KD-tree searches against everything around them.

    python -m benchmarks.contact_profile [--size 480x640] [--max-steps 120] [--json PATH]

The scripted ``transfer_cube`` episode of :mod:`benchmarks.contact_speed` (25 fps, three views,
MuJoCo's depth) at the given size, the robot rendered by the build's renderer, chunks of 8 future
steps. Every chunk runs :func:`~imac_data.core.contact.images.contact_chunk` with the build's
defaults on one thread (``parallel=1``, ``workers=1``), once to warm up, then under ``cProfile``.
The split, in CPU ms per future frame: the KD-tree searches (``NearestNeighbours._query_tree``),
the certified tiles' own tensor work around them (``certified_distances`` less its searches), and
the rest (scene cloud, lifting the robot pixels, building the trees, caps, colours, hole filling).
The searches are what the algorithm needs; the rest is what a fused kernel or a GPU could take away
(docs/building.md, "Contact: searches and glue").
"""

from __future__ import annotations

import argparse
import cProfile
import json
import pstats
import time
from pathlib import Path

import numpy as np
import torch

from benchmarks.contact_speed import CHUNK, episode
from imac_data.core.contact.images import chunk_plan, contact_chunk
from imac_data.core.rig import Rig
from imac_data.core.robot.aloha import robot_config
from imac_data.core.robot.model import RobotModel
from imac_data.sources.sim.rig import camera_calibration


def chunks(height: int, width: int, max_steps: int) -> list[tuple]:
    """The contact inputs of every chunk of the episode, as the build makes them."""
    sim = episode(max_steps, 0, height, width)
    ep = sim["ep"]
    rig = Rig(RobotModel(robot_config()), camera_calibration(sim["model"], width, height))
    depth = torch.stack([torch.as_tensor(ep.depth_mm[n].astype(np.float32) / 1000.0) for n in rig.names], 1)
    views = rig.robot_views(torch.as_tensor(ep.qpos, dtype=torch.float32))
    K = rig.intrinsics()
    out = []
    for ref, frames in chunk_plan(len(depth), CHUNK):
        frames = [f for f in frames if f != ref]
        if frames:
            out.append((depth[ref], K, views.T_world_cam[ref], views.mask[ref], views.depth[frames],
                        views.T_world_cam[frames], views.gripper_points[frames]))
    return out


def _cumulative(stats: pstats.Stats, name: str) -> float:
    return sum(v[3] for (_, _, fn), v in stats.stats.items() if fn == name)


def run(size: str = "480x640", max_steps: int = 120) -> dict:
    height, width = (int(x) for x in size.split("x"))
    torch.set_num_threads(1)
    inputs = chunks(height, width, max_steps)
    frames = sum(c[4].shape[0] for c in inputs)

    def all_chunks():
        for c in inputs:
            contact_chunk(*c, workers=1, parallel=1)

    all_chunks()  # warm-up: caches, allocator, imports
    cpu = time.process_time()
    profile = cProfile.Profile()
    profile.runcall(all_chunks)
    cpu = time.process_time() - cpu
    stats = pstats.Stats(profile)
    searches = _cumulative(stats, "_query_tree")
    certified = _cumulative(stats, "certified_distances")
    total = _cumulative(stats, "all_chunks")
    per_frame = 1e3 / frames
    return {"size": size, "future_frames": frames, "cpu_ms_per_frame": cpu * per_frame,
            "profiled_ms_per_frame": total * per_frame, "searches_ms_per_frame": searches * per_frame,
            "certified_tiles_other_ms_per_frame": (certified - searches) * per_frame,
            "rest_ms_per_frame": (total - certified) * per_frame, "searches_share": searches / total}


def report(r: dict) -> str:
    return (f"contact, {r['size']}, 3 views, one thread, {r['future_frames']} future frames: "
            f"{r['cpu_ms_per_frame']:.1f} CPU-ms a frame (profiled {r['profiled_ms_per_frame']:.1f})\n"
            f"  KD-tree searches                  {r['searches_ms_per_frame']:6.1f} ms ({100 * r['searches_share']:.0f} %)\n"
            f"  certified tiles, around them      {r['certified_tiles_other_ms_per_frame']:6.1f} ms\n"
            f"  the rest (clouds, trees, caps...) {r['rest_ms_per_frame']:6.1f} ms")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", default="480x640", help="HxW (default 480x640)")
    ap.add_argument("--max-steps", type=int, default=120, help="50 Hz steps of the episode (default 120)")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    r = run(args.size, args.max_steps)
    print(report(r))
    if args.json:
        args.json.write_text(json.dumps(r, indent=2) + "\n")


if __name__ == "__main__":
    main()
