"""``imac simulate``: record scripted gym-aloha episodes (RGB, depth, optional segmentation)
as ALOHA HDF5 files."""

from __future__ import annotations

import argparse
import time

from imac_data.console import run_command
from imac_data.sources.hdf5 import probe_episode
from imac_data.sources.sim.recorder import SimConfig, record_dataset


def run(args: argparse.Namespace) -> int:
    return run_command(lambda: _record(args))  # exit 2 bad input, 3 environment (disk full, ...)


def _record(args: argparse.Namespace) -> int:
    given = dict(task=args.task, num_episodes=args.episodes, width=args.width, height=args.height, seed=args.seed,
                 noise=args.noise, frame_stride=args.frame_stride, max_steps=args.max_steps)
    config = SimConfig(**{k: v for k, v in given.items() if v is not None}, with_depth=not args.no_depth,
                       with_segmentation=args.segmentation, compress=args.compress, shadows=args.shadows,
                       antialias=args.antialias)
    t0 = time.perf_counter()
    paths = record_dataset(config, args.out, progress=not args.quiet, overwrite=args.overwrite)
    seconds = time.perf_counter() - t0
    probes = [probe_episode(p) for p in paths]
    frames = sum(p["num_frames"] for p in probes)
    successes = sum(bool(p["info"].success) for p in probes)
    print(f"{config.task}: {len(paths)} episodes, {successes} successes, {frames} frames "
          f"({config.height}x{config.width}, {config.fps:g} fps) in {seconds:.1f} s -> {args.out}")
    return 0
