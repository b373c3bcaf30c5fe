"""A build worker's memory chunk by chunk along one long episode: what stays (the floor) and what each chunk
adds on top (its peak), and how each moves with the frame's position in the episode (docs/building.md,
"Workers, memory and speed").

A worker's whole-build peak mixes three things: memory kept for the episode so far, each chunk's working set,
and how the heap's free space fits the next chunk's arrays. This separates them. One worker (one thread, one
malloc arena, as the build runs it) writes a shard of a recorded 240x320 episode tiled to ``--frames``
(``tile_episode``), and at every chunk boundary, where the pipeline hands freed memory back
(``imac_data.augment.pipeline.release_freed_memory``, wrapped here), reads

* the **floor**: the resident memory just after the hand-back;
* the chunk's **peak**: the kernel's high-water mark ``VmHWM``, reset after every read (``/proc/self/clear_refs``).

It prints both as slopes in KB per frame of the episode, and the peaks' medians over the first and second halves.
``--mmap-threshold BYTES`` fixes glibc's threshold above which an allocation gets pages of its own (by default it
moves up to the largest block freed, so large arrays come to share the heap):

    python -m benchmarks.chunk_memory --frames 1500
    python -m benchmarks.chunk_memory --frames 1500 --mmap-threshold 1048576

Linux with glibc only (``/proc``, ``mallopt``). Run it on an idle machine: the CPU seconds are printed beside."""

from __future__ import annotations

import argparse
import ctypes
import ctypes.util
import json
import multiprocessing
import resource
import tempfile
import time
from pathlib import Path

import numpy as np

_M_MMAP_THRESHOLD = -3  # mallopt parameter (glibc malloc.h)


def _resident_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * resource.getpagesize() / 1e6


def _high_water_mb() -> float:
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) / 1e3 for line in f if line.startswith("VmHWM"))


def _reset_high_water() -> None:
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")  # resets VmHWM to the current resident size (Linux >= 4.0)


def record(out: Path) -> None:
    """One recorded 240x320 episode of 125 frames (in its own process: MuJoCo's renderer stays out of the figures)."""
    from imac_data.sources.sim.recorder import SimConfig, record_dataset

    record_dataset(SimConfig(num_episodes=1, max_steps=250), out, progress=False, overwrite=True)


def measure(frames: int, tmp: Path, *, mmap_threshold: int | None = None) -> dict:
    """One worker writes a ``frames``-frame shard; the floor and peak at every chunk boundary."""
    recorded = tmp / "recorded"
    child = multiprocessing.get_context("spawn").Process(target=record, args=(recorded,))
    child.start()
    child.join()
    if child.exitcode != 0:
        raise RuntimeError(f"recording the episode failed (exit code {child.exitcode})")
    from imac_data.console import limit_malloc_arenas, quiet_libraries

    limit_malloc_arenas()
    if mmap_threshold is not None:
        ctypes.CDLL(ctypes.util.find_library("c")).mallopt(_M_MMAP_THRESHOLD, int(mmap_threshold))
    import torch

    from imac_data.augment import pipeline
    from imac_data.build.streams import write_episode_dataset
    from imac_data.core.rig import Rig
    from imac_data.dataset.ingest import IngestOptions
    from imac_data.recipes import RECIPES_DIR, load_recipe
    from imac_data.sources.hdf5 import tile_episode

    quiet_libraries()
    torch.set_num_threads(1)
    episode = tile_episode(recorded / "episode_0.hdf5", tmp / f"tiled_{frames}.hdf5", frames)
    recipe = load_recipe(RECIPES_DIR / "aloha_sim_transfer_cube.yaml")
    rig = Rig.from_recipe(recipe, recorded / "calibration.json")

    floor, peak = [], []
    hand_back = pipeline.release_freed_memory

    def observed_hand_back() -> None:
        peak.append(_high_water_mb())
        hand_back()
        floor.append(_resident_mb())
        _reset_high_water()

    pipeline.release_freed_memory = observed_hand_back
    c0, t0 = time.process_time(), time.perf_counter()
    try:
        write_episode_dataset(episode, tmp / "shard", "local/chunk_memory", rig, recipe.augment,
                              IngestOptions(fps=25.0, task="transfer the cube"), threads=1)
    finally:
        pipeline.release_freed_memory = hand_back
    cpu_s, wall_s = time.process_time() - c0, time.perf_counter() - t0
    chunk = recipe.augment.contact_chunk
    position = np.arange(len(floor)) * chunk  # the chunk's first frame
    keep = position >= 5 * chunk  # the first chunks still allocate what stays (encoders, pools)
    half = len(peak) // 2

    def slope(values):
        return float(np.polyfit(position[keep], np.asarray(values)[keep], 1)[0] * 1e3)

    return {"frames": frames, "chunks": len(floor), "mmap_threshold": mmap_threshold,
            "cpu_ms_per_frame": 1e3 * cpu_s / frames, "wall_s": wall_s,
            "floor_mb_first_last": [floor[5], floor[-1]], "floor_kb_per_frame": slope(floor),
            "peak_median_mb_halves": [float(np.median(peak[5:half])), float(np.median(peak[half:]))],
            "peak_max_mb": float(max(peak)), "peak_kb_per_frame": slope(peak)}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.chunk_memory", description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=1500, help="the tiled episode's length (default 1500)")
    parser.add_argument("--mmap-threshold", type=int, default=None,
                        help="bytes; allocations above it get pages of their own (default: glibc's moving threshold)")
    parser.add_argument("--out", type=Path, default=None, help="also write the figures to this JSON file")
    args = parser.parse_args(argv)
    if args.frames < 80:
        parser.error("--frames must be at least 80 (ten chunks)")
    with tempfile.TemporaryDirectory(prefix="chunk_memory_") as tmp:
        r = measure(args.frames, Path(tmp), mmap_threshold=args.mmap_threshold)
    print(f"{r['frames']} frames, {r['chunks']} chunks, mmap threshold {r['mmap_threshold'] or 'glibc default'}: "
          f"{r['cpu_ms_per_frame']:.0f} CPU ms a frame, {r['wall_s']:.0f} s")
    print(f"  floor {r['floor_mb_first_last'][0]:.0f} -> {r['floor_mb_first_last'][1]:.0f} MB, "
          f"{r['floor_kb_per_frame']:.1f} KB a frame")
    print(f"  chunk peaks: median {r['peak_median_mb_halves'][0]:.0f} MB (first half) -> "
          f"{r['peak_median_mb_halves'][1]:.0f} MB (second), max {r['peak_max_mb']:.0f} MB, "
          f"{r['peak_kb_per_frame']:.1f} KB a frame")
    if args.out is not None:
        args.out.write_text(json.dumps(r, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
