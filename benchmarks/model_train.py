"""World-model training speed and memory on the CPU (by default the small backbone).

    python -m benchmarks.model_train [--quick] [--threads 2] [--json PATH]
    python -m benchmarks.model_train --config imac_model/configs/ranking.yaml --views 1 --sizes 48x64 --batch 8 --threads 1

Workload: one optimizer step (forward, flow loss, backward, AdamW) of
:class:`imac_model.models.world_model.WorldModel` with the small backbone of
``imac_model/configs/small_cpu.yaml`` (pixel-unshuffle 4, patch 4, dim 128, 4 blocks),
conditioning ``motion+contact`` (three control streams), a chunk of 1 + 8 frames,
batch 4, three views, at 64x64 and 128x128 per view (mosaics 128x192 and 256x384).
Inputs are random tensors of the real shapes: data loading is not timed (the trainer
keeps decoded chunks in memory). ``--config``, ``--views``, ``--sizes`` and ``--batch`` measure another
run's model (the second line: the ranking benchmark's U-Net on its one 48x64 view, batch 8).

Each size runs in its own process, so its peak resident memory is its own: reported
as the peak RSS and as the growth over the RSS just before the first step (model,
optimizer and batch built). Steps/s is the median over the timed steps after two
warm-up steps; CPU seconds per step are reported beside wall seconds because the
machine may be shared (load average at start and end). ``OMP_WAIT_POLICY`` defaults to
``PASSIVE`` here: on a busy machine spinning OpenMP threads cost up to 9x the CPU time. ``run()`` returns a flat dict
(``model_small_steps_per_s_64``, ``model_small_peak_rss_mb_64``, ...).
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import platform
import resource
import statistics
import time
from pathlib import Path

CONFIG = Path(__file__).resolve().parent.parent / "imac_model" / "configs" / "small_cpu.yaml"
SIZES = ((64, 64), (128, 128))  # per view, (height, width)
VIEWS = ("cam_high", "cam_left_wrist", "cam_right_wrist")
BATCH, CHUNK, ACTION_DIM = 4, 8, 14


def _rss_mb() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def _measure(size: tuple[int, int], steps: int, threads: int, config: Path, views: int, batch_size: int,
             queue) -> None:
    import torch

    from imac_model.config import ModelSpec, load_run_config
    from imac_model.data.batch import ChunkBatch
    from imac_model.models.world_model import WorldModel

    torch.set_num_threads(threads)
    run = load_run_config(config)
    spec = ModelSpec(backbone=run.backbone, conditioning=run.conditioning, flow=run.flow,
                     views=VIEWS[:views], view_height=size[0], view_width=size[1],
                     chunk=CHUNK, action_dim=ACTION_DIM, fps=25.0)
    torch.manual_seed(0)
    model = WorldModel(spec)
    opt = torch.optim.AdamW(model.parameters(), lr=1e-4)
    Hm, Wm = spec.mosaic_hw
    g = torch.Generator().manual_seed(0)
    B = batch_size
    batch = ChunkBatch(reference=torch.rand(B, 3, Hm, Wm, generator=g),
                       actions=torch.randn(B, CHUNK, ACTION_DIM, generator=g),
                       controls={s: torch.rand(B, CHUNK, 3, Hm, Wm, generator=g) for s in spec.conditioning.streams},
                       future=torch.rand(B, CHUNK, 3, Hm, Wm, generator=g))
    rss_before = _rss_mb()
    walls, cpus = [], []
    for i in range(steps + 2):
        t, c = time.perf_counter(), time.process_time()
        out = model(batch, generator=torch.Generator().manual_seed(i))
        out.loss.backward()
        opt.step()
        opt.zero_grad(set_to_none=True)
        if i >= 2:
            walls.append(time.perf_counter() - t)
            cpus.append(time.process_time() - c)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    queue.put({"size": size, "params_m": sum(p.numel() for p in model.parameters()) / 1e6,
               "tokens": (Hm // model.backbone.spatial_multiple) * (Wm // model.backbone.spatial_multiple)
               * (CHUNK + 1), "wall_s": statistics.median(walls), "cpu_s": statistics.median(cpus),
               "peak_rss_mb": peak, "rss_growth_mb": peak - rss_before})


def run(quick: bool = False, threads: int = 2, steps: int | None = None, config: Path = CONFIG,
        views: int = len(VIEWS), sizes: tuple[tuple[int, int], ...] | None = None, batch: int = BATCH) -> dict:
    steps = steps or (2 if quick else 8)
    sizes = sizes or (((32, 32), (64, 64)) if quick else SIZES)
    load_start = os.getloadavg()
    # OpenMP threads that spin while waiting burn a shared CPU (measured here: 2 threads on a busy
    # 2-core machine spent 9x the CPU time per step); passive waiting costs nothing on an idle one.
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    ctx = mp.get_context("spawn")
    result: dict = {"model_threads": threads, "model_batch": batch, "model_frames": CHUNK + 1, "model_views": views,
                    "model_config": str(Path(config).resolve().relative_to(CONFIG.parents[2])), "model_quick": quick,
                    "model_cpu": platform.processor() or platform.machine(),
                    "model_omp_wait_policy": os.environ["OMP_WAIT_POLICY"]}
    for size in sizes:
        queue = ctx.Queue()
        proc = ctx.Process(target=_measure, args=(size, steps, threads, Path(config), views, batch, queue))
        proc.start()
        r = queue.get()
        proc.join()
        key = f"_{_size_key(size)}"
        result.update({f"model_small_steps_per_s{key}": 1.0 / r["wall_s"], f"model_small_wall_s_per_step{key}":
                       r["wall_s"], f"model_small_cpu_s_per_step{key}": r["cpu_s"],
                       f"model_small_peak_rss_mb{key}": r["peak_rss_mb"],
                       f"model_small_rss_growth_mb{key}": r["rss_growth_mb"], f"model_small_tokens{key}": r["tokens"],
                       "model_small_params_m": r["params_m"]})
    result["model_sizes"] = [_size_key(s) for s in sizes]
    result["load_average_start_end"] = [round(x, 2) for x in load_start + os.getloadavg()]
    return result


def report(r: dict) -> str:
    lines = [f"World model ({r['model_config']}, {r['model_small_params_m']:.2f} M parameters), motion+contact, "
             f"{r.get('model_views', 3)} view(s), batch {r['model_batch']} x {r['model_frames']} frames, {r['model_threads']} "
             f"thread(s), OMP_WAIT_POLICY={r['model_omp_wait_policy']}; load average {r['load_average_start_end']}",
             "| per view | tokens | steps/s | wall s/step | CPU s/step | peak RSS MB | RSS growth MB |",
             "|---|---|---|---|---|---|---|"]
    for s in r["model_sizes"]:
        k = f"_{s}"
        label = s if isinstance(s, str) else f"{s}x{s}"
        lines.append(f"| {label} | {r['model_small_tokens' + k]} | {r['model_small_steps_per_s' + k]:.2f} | "
                     f"{r['model_small_wall_s_per_step' + k]:.2f} | {r['model_small_cpu_s_per_step' + k]:.2f} | "
                     f"{r['model_small_peak_rss_mb' + k]:.0f} | {r['model_small_rss_growth_mb' + k]:.0f} |")
    return "\n".join(lines)


def _size_key(size: tuple[int, int]) -> int | str:
    """How a size names its figures: 64 for 64x64 (the keys results saved before have), else "48x64"."""
    return size[0] if size[0] == size[1] else f"{size[0]}x{size[1]}"


def _size(text: str) -> tuple[int, int]:
    h, _, w = text.partition("x")
    try:
        return int(h), int(w or h)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: give HxW, for example 48x64") from None


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(prog="python -m benchmarks.model_train", description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true", help="32x32 and 64x64 per view, 2 timed steps")
    p.add_argument("--threads", type=int, default=2, help="torch threads (default 2: the CI machine's cores)")
    p.add_argument("--steps", type=int, help="timed steps per size (default 8)")
    p.add_argument("--config", type=Path, default=CONFIG, help="the run config whose model is measured")
    p.add_argument("--views", type=int, default=len(VIEWS), choices=range(1, len(VIEWS) + 1), help="views per sample")
    p.add_argument("--sizes", nargs="+", type=_size, help="per view, HxW (default 64x64 128x128)")
    p.add_argument("--batch", type=int, default=BATCH, help=f"samples per step (default {BATCH})")
    p.add_argument("--json", type=Path, help="also write the results here")
    args = p.parse_args(argv)
    r = run(quick=args.quick, threads=args.threads, steps=args.steps, config=args.config, views=args.views,
            sizes=tuple(args.sizes) if args.sizes else None, batch=args.batch)
    print(report(r))
    if args.json:
        args.json.write_text(json.dumps(r, indent=1))
    return r


if __name__ == "__main__":
    main()
