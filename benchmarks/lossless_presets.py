"""Lossless encoding of the derived streams at each x264 preset: CPU time per frame, size, and whether every frame
decodes to exactly the values it had (issue 65's "encode" stage; benchmarks/results/build_speed.md, "Encode: the lossless preset").

Reads a built dataset's lossless streams (depth, motion, contact; ``libx264rgb`` at qp 0), decodes them, and codes
the frames again with our own writer (``VideoWriter``) at each preset, one thread, as the build does:

    python -m benchmarks.lossless_presets --root ~/.cache/huggingface/lerobot/local/aloha_sim_transfer_cube

Run it on an idle machine: the figure is CPU time of this process alone (the encoder's threads included)."""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from imac_data.dataset.videos import VideoEncoding, VideoWriter, read_video_frames

PRESETS = ("medium", "fast", "faster", "veryfast", "superfast", "ultrafast")


def lossless_streams(root: Path) -> dict[str, Path]:
    """The dataset's h264 (lossless) videos by feature: every feature whose info names the codec h264."""
    info = json.loads((root / "meta" / "info.json").read_text())
    return {k: next((root / "videos" / k).rglob("*.mp4")) for k, f in info["features"].items()
            if f["dtype"] == "video" and (f.get("info") or {}).get("video.codec") == "h264"}


def encode_cpu_s(frames: np.ndarray, encoding: VideoEncoding, fps: int, out: Path) -> tuple[float, float, int, bool]:
    """CPU seconds to code ``frames`` and to decode them again (this process, all threads), bytes written, and
    whether they decode exactly."""
    c0 = time.process_time()
    writer = VideoWriter(out, encoding, fps, *frames.shape[1:3])
    writer.write(frames)
    writer.close()
    c1 = time.process_time()
    decoded = read_video_frames(out)
    return c1 - c0, time.process_time() - c1, out.stat().st_size, bool(np.array_equal(decoded, frames))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.lossless_presets", description=__doc__.split("\n\n")[0])
    p.add_argument("--root", type=Path, required=True, help="a built dataset")
    p.add_argument("--presets", nargs="+", default=list(PRESETS))
    p.add_argument("--frames", type=int, default=250, help="frames of each stream coded (its first)")
    p.add_argument("--out", type=Path, help="write the figures here as JSON")
    args = p.parse_args(argv)
    streams = lossless_streams(args.root)
    fps = json.loads((args.root / "meta" / "info.json").read_text())["fps"]
    frames = {k: read_video_frames(v)[:args.frames] for k, v in streams.items()}
    n = min(len(f) for f in frames.values())
    base = VideoEncoding(codec="libx264rgb", pix_fmt="rgb24", qp=0, gop=10, threads=1)
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        for preset in args.presets:
            cpu = dec = size = 0.0
            exact = True
            for k, f in frames.items():
                c, d, b, same = encode_cpu_s(f[:n], replace(base, preset=preset), fps, Path(tmp) / f"{preset}_{k}.mp4")
                cpu, dec, size, exact = cpu + c, dec + d, size + b, exact and same
            rows[preset] = {"cpu_ms_per_frame": 1000 * cpu / n, "decode_cpu_ms_per_frame": 1000 * dec / n,
                            "mb": size / 1e6, "exact": exact}
            print(f"{preset:>10}: {1000 * cpu / n:6.1f} CPU-ms a dataset frame to code ({len(frames)} streams), "
                  f"{1000 * dec / n:5.1f} to decode, {size / 1e6:6.2f} MB, decodes exactly: {exact}", flush=True)
    if args.out:
        args.out.write_text(json.dumps({"root": str(args.root), "frames": n, "streams": sorted(frames),
                                        "presets": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
