"""Depth stream fidelity: simulated ground-truth depth through the whole stored path.

    .venv/bin/python benchmarks/depth_fidelity.py [--episodes 2] [--width 320 --height 240]
        [--max-steps N] [--no-candidates] [--slow] [--markdown out.md] [--keep DIR]

Path: MuJoCo depth recorded by ``imac_data.sources.sim.recorder`` (uint16 millimetres, the
oracle) -> ``RecordedDepth`` -> ``add_depth_streams`` (codec ``manipulation`` +
encoder) -> ``LeRobotDataset`` with its default decoder (torchcodec) -> decode ->
metres. Errors are over pixels whose ground truth lies in [0.1, 1.2] m, whole
episodes, all three cameras. The same frames go through the same path once more
with LeRobot's own encoder settings (libsvtav1, yuv420p, crf 30, gop 2, preset 12)
for comparison; "validity flips" counts pixels that are valid in one and invalid
in the other.

The candidate table (skip with ``--no-candidates``) encodes the same codec frames
with each candidate setting straight to mp4 (``encode_video``) and decodes them with
torchcodec as LeRobot does (``VideoDecoder(seek_mode="approximate")``) and with
PyAV; it is what the depth stream's settings were chosen from. ``--slow`` adds
libaom AV1 4:4:4 (about 20 fps here).

``run(...)`` returns the figures as a dict (``depth_err_median_mm``,
``depth_err_p99_mm``, ``depth_err_p99_mm_lerobot_default``, sizes, ...).
"""

from __future__ import annotations

import argparse
import os
import platform
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

os.environ.setdefault("MUJOCO_GL", "egl")

from imac_data.core.depth import DepthCodec  # noqa: E402
from imac_data.dataset.depth_streams import add_depth_streams  # noqa: E402
from imac_data.dataset.videos import VideoEncoding, encode_video, read_video_frames  # noqa: E402
from imac_data.layout import depth_key

NEAR, FAR = 0.1, 1.2
CAMS = ("cam_high", "cam_left_wrist", "cam_right_wrist")


def candidates(slow: bool = False) -> list[tuple[str, VideoEncoding | None, str]]:
    """(label, settings, note). ``None`` settings: not encodable into mp4 (reported)."""
    x = VideoEncoding
    rows = [
        ("LeRobot default: svtav1 yuv420p crf30 g2", x.lerobot_default(), ""),
        ("x264 yuv444p crf0 g2", x("libx264", "yuv444p", crf=0, qp=None, preset="medium", gop=2), ""),
        ("x264 yuv444p qp0 g10", x("libx264", "yuv444p", qp=0, preset="medium", gop=10), ""),
        ("x264 yuv444p crf10 g10", x("libx264", "yuv444p", crf=10, qp=None, preset="medium", gop=10), ""),
        ("x264rgb rgb24 qp0 g2", x.lossless_rgb(gop=2), ""),
        ("x264rgb rgb24 qp0 g10 (chosen)", x.lossless_rgb(gop=10), ""),
        ("x264rgb rgb24 qp0 g25", x.lossless_rgb(gop=25), ""),
        ("x264rgb rgb24 qp0 g250", x.lossless_rgb(gop=250), ""),
        ("x264rgb rgb24 qp0 g10 slow", x.lossless_rgb(gop=10, preset="slow"), ""),
        ("x264rgb rgb24 crf4 g10", x("libx264rgb", "rgb24", crf=4, qp=None, preset="medium", gop=10), ""),
        ("x265 gbrp lossless g10", x("libx265", "gbrp", qp=None, preset="medium", gop=10,
                                     options={"x265-params": "lossless=1:log-level=error"}), ""),
        ("ffv1", None, "FFmpeg's mp4 muxer does not take FFV1"),
        ("svtav1 yuv444p", None, "libsvtav1 encodes yuv420p / yuv420p10le only"),
    ]
    if slow:
        rows.append(("aom-av1 yuv444p crf0 g10", x("libaom-av1", "yuv444p", crf=0, qp=None, preset=None, gop=10,
                                                   options={"cpu-used": "8", "row-mt": "1"}), ""))
    return rows


def error_stats(decoded: list[np.ndarray], truth: list[np.ndarray]) -> dict:
    errs, flips, total = [], 0, 0
    for d, gt in zip(decoded, truth):
        m = (gt >= NEAR) & (gt <= FAR)
        errs.append(np.abs(d[m].astype(np.float64) - gt[m]))
        flips += int(((d > 0) != (gt > 0)).sum())
        total += gt.size
    e = np.concatenate(errs) * 1000.0
    return {"median_mm": float(np.median(e)), "mean_mm": float(e.mean()), "p99_mm": float(np.percentile(e, 99)),
            "max_mm": float(e.max()), "pixels": int(e.size), "validity_flips": flips / total}


def record(workdir: Path, episodes: int, width: int, height: int, max_steps: int | None) -> tuple[Path, Path]:
    from imac_data.build.from_episodes import ingest_episodes
    from imac_data.core.cameras import load_calibration
    from imac_data.core.rig import Rig
    from imac_data.core.robot import aloha
    from imac_data.core.robot.model import RobotModel
    from imac_data.dataset.ingest import IngestOptions
    from imac_data.sources.hdf5 import episode_paths
    from imac_data.sources.sim.recorder import SimConfig, record_dataset

    src, base = workdir / "src", workdir / "base"
    record_dataset(SimConfig(num_episodes=episodes, width=width, height=height, max_steps=max_steps), src,
                   progress=False)
    rig = Rig(RobotModel(aloha.robot_config()), load_calibration(src / "calibration.json"))
    ingest_episodes(episode_paths(src), rig=rig, repo_id="local/depth_fidelity", root=base,
                    options=IngestOptions(fps=25, task="transfer", state_names=aloha.STATE_NAMES), progress=False)
    return src, base


def through_dataset(src: Path, base: Path, root: Path, encoding: VideoEncoding, codec: DepthCodec) -> dict:
    """add_depth_streams -> LeRobotDataset (default decoder) -> decode; errors and sizes."""
    from imac_data import lerobot_compat as lr
    from imac_data.core.cameras import load_calibration
    from imac_data.core.rig import Rig
    from imac_data.core.robot import aloha
    from imac_data.core.robot.model import RobotModel
    from imac_data.sources.depth import RecordedDepth, episode_views
    from imac_data.sources.hdf5 import episode_paths, read_episode

    shutil.copytree(base, root)
    paths = episode_paths(src)
    source = RecordedDepth(cameras=list(CAMS))
    calib = load_calibration(src / "calibration.json")
    robot = RobotModel(aloha.robot_config())

    def episodes():
        for p in paths:
            yield source.depth(episode_views(read_episode(p), Rig(robot, calib), name=p.name))

    t0 = time.perf_counter()
    add_depth_streams(root, episodes(), cameras=list(CAMS), codec=codec, encoding=encoding,
                      source=source.describe())
    t_add = time.perf_counter() - t0
    ds = lr.LeRobotDataset("local/depth_fidelity", root=root)
    decoded, truth = [], []
    t0 = time.perf_counter()
    index = 0
    for p in paths:
        raw = read_episode(p, load_depth=True)
        for t in range(raw.num_frames):
            item = ds[index]
            index += 1
            for cam in CAMS:
                decoded.append(codec.decode(item[depth_key(cam)], channel_axis=-3).numpy())
                truth.append(raw.depth_mm[cam][t].astype(np.float32) / 1000.0)
    t_load = time.perf_counter() - t0
    size = sum(f.stat().st_size for cam in CAMS for f in (root / "videos" / depth_key(cam)).rglob("*.mp4"))
    rgb = sum(f.stat().st_size for cam in CAMS for f in (root / "videos" / f"observation.images.{cam}").rglob("*.mp4"))
    frames = len(truth)
    return {**error_stats(decoded, truth), "bytes": size, "kb_per_frame": size / frames / 1024, "frames": frames,
            "rgb_kb_per_frame": rgb / frames / 1024, "add_s": t_add, "load_s": t_load}


def candidate_rows(src: Path, workdir: Path, codec: DepthCodec, slow: bool) -> list[dict]:
    from torchcodec.decoders import VideoDecoder

    from imac_data.sources.hdf5 import episode_paths, read_episode

    clips = []  # (codec frames, ground truth metres) per episode and camera
    for p in episode_paths(src):
        raw = read_episode(p)
        for cam in CAMS:
            gt = raw.depth_mm[cam].astype(np.float32) / 1000.0
            clips.append((codec.encode_uint8(gt), gt))
    rng = np.random.default_rng(0)
    rows = []
    for label, enc, note in candidates(slow):
        if enc is None:
            rows.append({"label": label, "note": note})
            continue
        dec_tc, dec_av, truth = [], [], []
        size = frames = 0
        t_enc = t_ra = 0.0
        n_ra = 0
        exact = True
        for i, (colours, gt) in enumerate(clips):
            path = workdir / f"cand_{i}.mp4"
            t0 = time.perf_counter()
            encode_video(path, colours, fps=25, encoding=enc)
            t_enc += time.perf_counter() - t0
            size += path.stat().st_size
            frames += len(colours)
            decoder = VideoDecoder(str(path), seek_mode="approximate")  # as LeRobot opens it
            tc = decoder.get_frames_at(indices=list(range(len(colours)))).data.permute(0, 2, 3, 1).numpy()
            exact &= bool(np.array_equal(tc, colours))
            dec_tc.extend(codec.decode(tc))
            dec_av.extend(codec.decode(read_video_frames(path)))
            truth.extend(gt)
            decoder = VideoDecoder(str(path), seek_mode="approximate")
            t0 = time.perf_counter()
            for k in rng.integers(0, len(colours), 10):
                decoder.get_frames_at(indices=[int(k)])
            t_ra += time.perf_counter() - t0
            n_ra += 10
            path.unlink()
        tc_stats = error_stats(dec_tc, truth)
        av_stats = error_stats(dec_av, truth)
        rows.append({"label": label, **tc_stats, "pyav_p99_mm": av_stats["p99_mm"], "pyav_max_mm": av_stats["max_mm"],
                     "bit_exact": exact, "kb_per_frame": size / frames / 1024, "encode_fps": frames / t_enc,
                     "random_access_ms": 1000 * t_ra / n_ra, "note": note})
    return rows


def run(episodes: int = 2, width: int = 320, height: int = 240, max_steps: int | None = None,
        with_candidates: bool = True, slow: bool = False, keep: str | Path | None = None) -> dict:
    codec = DepthCodec.preset("manipulation")
    tmp = Path(keep) if keep else Path(tempfile.mkdtemp(prefix="depth_fidelity_"))
    tmp.mkdir(parents=True, exist_ok=True)
    try:
        t0 = time.perf_counter()
        src, base = record(tmp, episodes, width, height, max_steps)
        t_record = time.perf_counter() - t0
        ours = through_dataset(src, base, tmp / "ours", VideoEncoding.lossless_rgb(), codec)
        lerobot = through_dataset(src, base, tmp / "lerobot_default", VideoEncoding.lerobot_default(), codec)
        rows = candidate_rows(src, tmp, codec, slow) if with_candidates else []
    finally:
        if not keep:
            shutil.rmtree(tmp, ignore_errors=True)
    result = {
        "episodes": episodes, "resolution": [height, width], "frames": ours["frames"], "record_s": t_record,
        "encoding": VideoEncoding.lossless_rgb().to_dict(), "codec": codec.to_dict(),
        "depth_err_median_mm": ours["median_mm"], "depth_err_mean_mm": ours["mean_mm"],
        "depth_err_p99_mm": ours["p99_mm"], "depth_err_max_mm": ours["max_mm"],
        "validity_flips": ours["validity_flips"],
        "depth_err_median_mm_lerobot_default": lerobot["median_mm"],
        "depth_err_mean_mm_lerobot_default": lerobot["mean_mm"],
        "depth_err_p99_mm_lerobot_default": lerobot["p99_mm"],
        "depth_err_max_mm_lerobot_default": lerobot["max_mm"],
        "validity_flips_lerobot_default": lerobot["validity_flips"],
        "bytes": ours["bytes"], "bytes_lerobot_default": lerobot["bytes"],
        "kb_per_frame": ours["kb_per_frame"], "kb_per_frame_lerobot_default": lerobot["kb_per_frame"],
        "rgb_kb_per_frame": ours["rgb_kb_per_frame"], "pixels": ours["pixels"],
        "add_s": ours["add_s"], "load_s": ours["load_s"],
        "candidates": rows,
    }
    return result


def tables(r: dict) -> str:
    lines = [
        f"Depth through the stored path: {r['episodes']} simulated episode(s), {r['frames']} frames "
        f"(3 cameras x {r['frames'] // 3}) at {r['resolution'][0]}x{r['resolution'][1]}, "
        f"{r['pixels']} valid pixels in [{NEAR}, {FAR}] m; {platform.node()}",
        "",
        "| settings | median mm | mean mm | p99 mm | max mm | validity flips | KB/frame | MB total |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for label, suffix in (("ours: libx264rgb rgb24 qp0 gop10", ""),
                          ("LeRobot default: libsvtav1 yuv420p crf30 gop2", "_lerobot_default")):
        lines.append(
            f"| {label} | {r['depth_err_median_mm' + suffix]:.2f} | {r['depth_err_mean_mm' + suffix]:.2f} | "
            f"{r['depth_err_p99_mm' + suffix]:.2f} | {r['depth_err_max_mm' + suffix]:.1f} | "
            f"{r['validity_flips' + suffix]:.2%} | {r['kb_per_frame' + suffix]:.2f} | "
            f"{r['bytes' + suffix] / 2**20:.2f} |"
        )
    lines.append(f"\n(LeRobot's RGB streams of the same dataset: {r['rgb_kb_per_frame']:.2f} KB/frame; "
                 f"adding the 3 depth streams took {r['add_s']:.1f} s, reading them back {r['load_s']:.1f} s.)")
    if r["candidates"]:
        lines += ["", "Candidate encoder settings (same frames; errors via torchcodec, as LeRobot decodes):", "",
                  "| settings | bit-exact | median mm | p99 mm | max mm | PyAV p99 / max mm | KB/frame | "
                  "encode fps | random access ms |",
                  "|---|---|---|---|---|---|---|---|---|"]
        for c in r["candidates"]:
            if "median_mm" not in c:
                lines.append(f"| {c['label']} | - | - | - | - | - | - | - | - ({c['note']}) |")
                continue
            lines.append(
                f"| {c['label']} | {'yes' if c['bit_exact'] else 'no'} | {c['median_mm']:.2f} | {c['p99_mm']:.2f} | "
                f"{c['max_mm']:.1f} | {c['pyav_p99_mm']:.2f} / {c['pyav_max_mm']:.1f} | {c['kb_per_frame']:.2f} | "
                f"{c['encode_fps']:.0f} | {c['random_access_ms']:.1f} |"
            )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--episodes", type=int, default=2)
    p.add_argument("--width", type=int, default=320)
    p.add_argument("--height", type=int, default=240)
    p.add_argument("--max-steps", type=int, default=None, help="cap on 50 Hz steps per episode (default: whole)")
    p.add_argument("--no-candidates", action="store_true")
    p.add_argument("--slow", action="store_true", help="also libaom AV1 4:4:4 (slow)")
    p.add_argument("--markdown", type=Path)
    p.add_argument("--keep", type=Path, help="work in this directory and keep it")
    a = p.parse_args(argv)
    r = run(a.episodes, a.width, a.height, a.max_steps, not a.no_candidates, a.slow, a.keep)
    text = tables(r)
    print(text)
    if a.markdown:
        a.markdown.write_text(text + "\n")
    return r


if __name__ == "__main__":
    main()
