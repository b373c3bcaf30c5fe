"""Cost of the video metrics on this machine (CPU, or CUDA when present).

    python -m benchmarks.evaluate_video_metrics [--samples 4] [--frames 9] [--size 224] [--device cpu]

Three views of ``--size`` squared (the public iMaC release's view size), mosaic of one
row, ``--samples`` generated/recorded video pairs of ``--frames`` frames. The FID and
FVD extractors are the real architectures with random weights (their cost does not
depend on the weights). Reports wall and CPU seconds per call and per frame / video,
and the load average.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import torch


def timed(fn):
    t, c = time.perf_counter(), time.process_time()
    out = fn()
    if torch.cuda.is_available():
        torch.cuda.synchronize()
    return out, time.perf_counter() - t, time.process_time() - c


def main(argv=None) -> int:
    from imac_model.evaluate.video_metrics import (
        VideoMetricsConfig,
        compute_video_metrics,
        load_fid_extractor,
        load_fvd_extractor,
        save_random_weights,
    )

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--samples", type=int, default=4)
    ap.add_argument("--frames", type=int, default=9)
    ap.add_argument("--size", type=int, default=224)
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    ap.add_argument("--metrics", default="pixel,fid,fvd", help="comma-separated groups: pixel, fid, fvd")
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    print(f"load average at start: {os.getloadavg()}; torch threads {torch.get_num_threads()}; device {args.device}")
    with tempfile.TemporaryDirectory() as tmp:
        fid = load_fid_extractor(save_random_weights("fid", Path(tmp) / "fid.pth"), device=args.device)
        fvd = load_fvd_extractor(save_random_weights("fvd", Path(tmp) / "fvd.pt"), device=args.device)
    g = torch.Generator().manual_seed(0)
    shape = (args.samples, args.frames, 3, args.size, args.size)
    views = ("cam_high", "cam_left_wrist", "cam_right_wrist")
    rec = {v: torch.rand(shape, generator=g) for v in views}
    gen = {v: (x + 0.05 * torch.randn(x.shape, generator=g)).clamp(0, 1) for v, x in rec.items()}
    frames = args.samples * args.frames * (len(views) + 1)  # per side, views + mosaic
    videos = args.samples * (len(views) + 1)
    groups = {"pixel": ("mse", "psnr", "ssim"), "fid": ("fid",), "fvd": ("fvd",)}
    for metrics in (groups[g] for g in args.metrics.split(",")):
        config = VideoMetricsConfig(metrics=metrics, device=args.device)
        _, wall, cpu = timed(lambda: compute_video_metrics(gen, rec, config=config, fid_extractor=fid,
                                                           fvd_extractor=fvd))
        unit, n = ("video pair", videos) if metrics == ("fvd",) else ("frame pair", frames)
        print(f"{'+'.join(metrics):>14}: {wall:7.2f} s wall, {cpu:7.2f} s CPU; "
              f"{1e3 * wall / n:8.1f} ms wall / {1e3 * cpu / n:8.1f} ms CPU per {unit} (views + mosaic)", flush=True)
    print(f"load average at end: {os.getloadavg()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
