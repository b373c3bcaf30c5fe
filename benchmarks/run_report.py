"""The Markdown report of :mod:`benchmarks.run`: ``latest.md`` from the ``latest.json`` it wrote.

``python -m benchmarks.run --from-json benchmarks/results/latest.json`` re-renders it alone.
"""

from __future__ import annotations

import math
import os

REQUIRED_NUMBERS = (
    "fps_total_240", "cpu_ms_per_frame_240", "peak_mem_mb_per_worker", "fps_total_480", "cpu_ms_per_frame_480",
    "fps_ray_240", "long_episode_peak_mb", "short_episode_peak_mb", "long_episode_fps",
    "render_ms_per_view_240", "render_ratio_vs_mujoco", "contact_fps_cpu", "contact_ratio_vs_reference",
    "depth_err_median_mm", "depth_err_p99_mm", "depth_err_p99_mm_lerobot_default", "mask_iou_head",
    "mask_iou_wrist_min", "contact_err_max_mm_under_5cm",
)


STREAM_GROUPS = {
    "rgb (LeRobot encoder)": "observation.images.",
    "depth": "observation.depth.",
    "motion": "control.motion.",
    "contact_r2s": "control.contact_r2s.",
    "contact_s2g": "control.contact_s2g.",
}


STAGE_LABELS = {
    "setup": "setup per worker (rig from the dataset block: robot, renderer scene, gripper samples)",
    "read": "read (HDF5 frames of the chunk: RGB, depth)",
    "fk": "FK (drawn configurations, reference state, camera poses)",
    "render": "render (drawn configurations; the reference state once per chunk)",
    "depth": "depth (mm -> m, resize, colour codec)",
    "contact": "contact (both streams, caps, colours)",
    "encode": "encode (3 RGB svtav1 + 12 lossless x264rgb streams, LeRobot's frame writer)",
    "write": "write (dataset metadata: LeRobot's save/finalize, stream commit, caps column, imac block)",
    "merge": "merge the episode shards (aggregate_datasets, imac block, robot description, card)",
    "validate": "validate the result (imac_data.dataset.validate, sampled frames)",
    "other": "other = build wall - stages / workers (start-up, worker spawn and imports, input checks, moves)",
}


def tag(size) -> str:
    return f"{size[0]}x{size[1]}"


def _f(v, fmt=".3g", none="-"):
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return none
    return format(v, fmt)


def same_host_table(builds: list[dict]) -> list[str]:
    """The builds of a :mod:`benchmarks.same_host` comparison as a Markdown table and its footnote."""
    lines = ["| size | round | workers | revision | frames | build s | frames/s | CPU ms/frame | peak RSS MB | "
             "load start -> end |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in builds:
        lines.append(f"| {r['size']} | {r['round']} | {r['workers']} | {r['revision']} | {r['frames']} | "
                     f"{r['build_s'] or r['cli_wall_s']:.1f} | {r['fps']:.2f} | {r['cpu_ms_per_frame']:.0f} | "
                     f"{r['peak_rss_mb']:.0f} | {r['load_avg_start'][0]:.2f} -> {r['load_avg_end'][0]:.2f} |")
    lines.append("\n(build s: what the CLI prints; CPU: the CLI process and the workers it reaped (`wait4`); peak "
                 "RSS: the largest of those processes.)")
    return lines


def ratio_lines(summary: dict) -> list[str]:
    """One bullet per size of a :mod:`benchmarks.same_host` summary: each revision's best setting, the ratio."""
    lines = []
    for size, s in summary.items():
        b, t = s["best"]["baseline"], s["best"]["this"]
        pairs = ", ".join(f"{p['fps_ratio']:.2f}x (round {p['round']}, {p['workers']} w)" for p in s["pairs"])
        lines.append(f"* **{size}**: best setting, median over rounds: baseline {b['fps']:.2f} frames/s "
                     f"({b['workers']} worker(s), {b['cpu_ms_per_frame']:.0f} CPU ms/frame), this {t['fps']:.2f} "
                     f"({t['workers']} worker(s), {t['cpu_ms_per_frame']:.0f} CPU ms/frame): **{s['fps_ratio_best']:.2f}x** "
                     f"frames/s, {s['cpu_ratio_best']:.2f}x CPU per frame. Same-round pairs: {pairs}.")
    return lines


def markdown(r: dict) -> str:
    w = r["workload"]
    small, large = w["key_sizes"]["_240"], w["key_sizes"]["_480"]
    L = [f"# imac benchmark{' (--quick smoke run: tiny sizes, figures not meaningful)' if r['quick'] else ''}", ""]
    L.append(f"`python -m benchmarks.run{' --quick' if r['quick'] else ''}` on {r['date']}, commit `{r['commit'][:12]}`"
             + (f" (+ uncommitted changes in {', '.join(r['commit_dirty_files'])})" if r["commit_dirty_files"] else "")
             + f"; {r['machine']}; {r['seconds'] / 60:.1f} min in all.")
    la = r["load_avg"]
    L.append(f"Load average (1/5/15 min) at start {la['start']}, at end {la['end']} on {os.cpu_count()} cores "
             "(per build below): where it exceeds the core count the machine was shared and wall-clock figures are "
             "low; CPU ms per frame are the steadier figure.")
    fpe = w.get("frames_per_episode")
    L.append(f"Workload: {w['episodes']} scripted `{w['task']}` episodes (noise {w['noise']}, seeds {w['seed']}..), "
             f"{_f(fpe, '.0f')} frames each at 25 fps, 3 views, recorded depth, at {small} and {large}; one frame = "
             "3 views x (base RGB + depth + motion + contact r2s + contact s2g).")
    cr = r.get("contact_vs_reference") or {}

    def _headline():
        nonlocal L
        L += ["", "## Headline figures", "", "| key | value | what |", "|---|---|---|"]
        what = {
            "fps_total_240": f"whole build (`build()`), frames/s, {small}, best local worker setting",
            "cpu_ms_per_frame_240": "CPU ms per frame of that build (build process + workers)",
            "peak_mem_mb_per_worker": "peak RSS of the largest worker in that build",
            "fps_total_480": f"whole build, frames/s, {large}, best local worker setting",
            "cpu_ms_per_frame_480": "CPU ms per frame of that build",
            "fps_ray_240": f"whole build with `--executor ray`, {w['ray_workers']} workers, {small}",
            "long_episode_peak_mb": f"peak RSS of the worker building one {w['long_frames']}-frame episode at "
                                    f"{w['long_size'][0]}x{w['long_size'][1]}",
            "short_episode_peak_mb": f"the same for its first {w['short_frames']} frames",
            "long_episode_fps": f"frames/s of the {w['long_frames']}-frame episode (1 worker)",
            "render_ms_per_view_240": f"our renderer, ms per view ({small if r['quick'] else '240x320'}, batched)",
            "render_ratio_vs_mujoco": "ours / MuJoCo's own GL RGB pass, time per view (lower = ours faster)",
            "contact_fps_cpu": "contact images, future frames/s (3 views, 240x320, CPU)",
            "contact_ratio_vs_reference": "ours / reference, time per future frame (reference: trimesh sampling "
                                          "+ scipy KD-trees per frame; lower = ours faster)",
            "depth_err_median_mm": "depth stream error through LeRobotDataset, median",
            "depth_err_p99_mm": "same, 99th percentile",
            "depth_err_p99_mm_lerobot_default": "LeRobot's default encoder, 99th percentile",
            "mask_iou_head": "motion-image robot mask vs MuJoCo segmentation, head camera (mean IoU)",
            "mask_iou_wrist_min": "same, worse of the two wrist cameras",
            "contact_err_max_mm_under_5cm": "s2g vs MuJoCo mj_geomDistance where under 5 cm, max abs error",
        }
        for k in REQUIRED_NUMBERS:
            note = f" (not measured: {r['not_measured'][k]})" if k in r["not_measured"] else ""
            L.append(f"| `{k}` | {_f(r[k], '.4g')} | {what[k]}{note} |")

    def _whole_build():
        nonlocal L
        L += ["", "## Whole build (`imac_data.build.hdf5.build`, end to end, fresh process)", "",
              "| size | executor | workers x threads | episodes | frames | build s | frames/s | CPU ms/frame | "
              "peak RSS per worker MB | coordinator MB | output KB/frame | load start -> end |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for b in r["builds"]:
            L.append(f"| {tag(b['size'])} | {b['executor']} | {b['workers']} x {b['threads']} | {b['episodes']} | "
                     f"{b['frames']} | {b['build_s']:.1f} | {b['fps']:.2f} | {b['cpu_ms_per_frame']:.0f} | "
                     f"{b['peak_mem_mb_per_worker']:.0f} | {b['peak_mem_mb_coordinator']:.0f} | "
                     f"{b['bytes_per_frame']['total'] / 1024:.1f} | {b['load_avg_start'][0]} -> {b['load_avg_end'][0]} |")
        L.append("\n(build s: `build()` alone; CPU: the build process and its pool workers (`getrusage`), for Ray its "
                 "workers' own CPU from the build's timings; peak RSS per worker: each worker's peak (`VmHWM`) at the "
                 "end of its episodes, as the build records it; with 1 worker the build process is the worker.)")
        for size in {tag(b["size"]) for b in r["builds"]}:
            ws = {b["workers"]: b for b in r["builds"] if tag(b["size"]) == size and b["executor"] == "local"}
            if 1 in ws and 2 in ws:
                L.append(f"\n* {size}: 2 workers / 1 worker = {ws[2]['fps'] / ws[1]['fps']:.2f}x frames/s, "
                         f"{ws[2]['cpu_ms_per_frame'] / ws[1]['cpu_ms_per_frame']:.2f}x CPU per frame.")

    def _against_baseline():
        nonlocal L
        c = r.get("same_host")
        if not c:
            return
        L += ["", f"## Against `{c['baseline']}` on this machine, in this run", "",
              f"The same recorded episodes built by this checkout's command line and by `{c['baseline']}`'s (a "
              "temporary `git worktree`), each in a fresh process, the order alternating "
              "(`benchmarks.same_host.compare`); only the ratio carries to another machine.", "",
              *same_host_table(c["builds"]), "", *ratio_lines(c["summary"])]

    def _stages():
        nonlocal L
        sizes = list(r.get("stages") or {})
        L += ["", "## Time per stage (the 1-worker builds' own stage timings)", "",
              "A stage's CPU is the process's CPU while it runs, so work that other threads do meanwhile counts "
              "in it too: LeRobot's SVT-AV1 encoders finish frames asynchronously, and thread pools cost CPU "
              "between calls. Small stages (FK above all) therefore read high in 1-worker builds, whose pools run "
              "a thread per core; the total is exact.", ""]
        hdr = "| stage | " + " | ".join(f"{s} wall ms/frame | {s} CPU ms/frame | {s} CPU share" for s in sizes) + " |"
        L += [hdr, "|---|" + "---|" * (3 * len(sizes))]
        keys = []
        for s in sizes:
            keys += [k for k in r["stages"][s]["rows"] if k not in keys]
        order = [k for k in STAGE_LABELS if k in keys] + [k for k in keys if k not in STAGE_LABELS]
        for k in order:
            cells = []
            for s in sizes:
                row = r["stages"][s]["rows"].get(k)
                cells += ["-", "-", "-"] if row is None else [
                    _f(row["wall_ms_per_frame"], ".1f"), _f(row["cpu_ms_per_frame"], ".1f"),
                    _f(100 * (row["cpu_share"] or 0), ".0f") + " %"]
            L.append(f"| {STAGE_LABELS.get(k, k)} | " + " | ".join(cells) + " |")
        L.append("| **total CPU per frame** | " + " | ".join(
            f" | {r['stages'][s]['cpu_ms_per_frame']:.0f} | 100 %" for s in sizes) + " |")
        for s, g in (r.get("gap_to_30fps") or {}).items():
            L.append(f"\n**{s}, what stands between this and {g['target_fps']:.0f} frames/s:** on {g['cores']} cores "
                     f"that is a CPU budget of {g['budget_cpu_ms_per_frame']:.0f} ms per frame; the build uses "
                     f"{g['cpu_ms_per_frame']:.0f} ({g['over_budget_x']:.1f}x). Largest: "
                     + ", ".join(f"{k} {v:.0f} ms" for k, v in g["largest"]) + ".")

    def _length():
        nonlocal L
        e = r.get("episode_length") or {}
        if not e:
            return
        L += ["", f"## Episode length ({e['size'][0]}x{e['size'][1]}, one worker, one episode)", "",
              "| frames | build s | frames/s | CPU ms/frame | peak RSS MB | load start -> end |",
              "|---|---|---|---|---|---|"]
        for n, row in e["rows"].items():
            L.append(f"| {n} | {row['build_s']:.1f} | {row['fps']:.2f} | {row['cpu_ms_per_frame']:.0f} | "
                     f"{row['peak_mem_mb_per_worker']:.0f} | {row['load_avg_start'][0]} -> {row['load_avg_end'][0]} |")
        L.append(f"\nPeak RSS, long / short episode: {e['peak_ratio_long_vs_short']:.3f} (synthetic episodes: a "
                 "recorded one played forward and backward, `aloha_hdf5.tile_episode`).")

    def _output_bytes():
        nonlocal L
        L += ["", "## Output bytes per frame (3 views)", "",
              "| size | " + " | ".join(STREAM_GROUPS) + " | tabular (parquet + meta) | total |",
              "|---|" + "---|" * (len(STREAM_GROUPS) + 2)]
        seen = set()
        for b in r["builds"]:
            if tag(b["size"]) in seen:
                continue
            seen.add(tag(b["size"]))
            bp = b["bytes_per_frame"]
            L.append(f"| {tag(b['size'])} | " + " | ".join(f"{bp[g] / 1024:.1f} KB" for g in STREAM_GROUPS)
                     + f" | {bp['tabular'] / 1024:.1f} KB | {bp['total'] / 1024:.1f} KB |")
        L.append("\n(tabular includes the robot description under `meta/imac/robot/`, about 1.5 MB per dataset.)")

    def _side_by_side():
        nonlocal L
        rv = r["render_vs_mujoco"]
        L += ["", "## Side by side", "", "**Renderer vs MuJoCo's own OpenGL renderer** (EGL, Mesa on the CPU; "
              "ms per view)", ""]
        if rv.get("timing_ms_per_view"):
            L += ["| size | ours (batch) | ours (1 frame) | MuJoCo RGB | MuJoCo depth | MuJoCo seg | MuJoCo RGB, "
                  "gym-aloha settings | ours / MJ RGB | ours / MJ all passes |",
                  "|---|---|---|---|---|---|---|---|---|"]
            for size, t in rv["timing_ms_per_view"].items():
                allp = t["mj_rgb"] + t["mj_depth"] + t["mj_seg"]
                L.append(f"| {size} | {t['ours_batch']:.2f} | {t['ours_single']:.2f} | {t['mj_rgb']:.2f} | "
                         f"{t['mj_depth']:.2f} | {t['mj_seg']:.2f} | {t['mj_rgb_shipped']:.1f} | "
                         f"{t['ours_batch'] / t['mj_rgb']:.2f} | {t['ours_batch'] / allp:.2f} |")
        L.append(f"\nOurs = RGB + mask + depth + link ids in one pass. Mask IoU vs MuJoCo: head "
                 f"{_f(rv.get('mask_iou_head'), '.4f')}, wrist min {_f(rv.get('mask_iou_wrist_min'), '.4f')} "
                 f"({rv.get('how', '')}).")
        L += ["", "**Contact builder vs a straightforward implementation** (trimesh 3000 samples per mesh + scipy "
              "KD-trees both ways, per frame; `benchmarks/contact_speed.py`)", ""]
        if "error" in cr:
            L.append(f"not run: {cr['error']}")
        else:
            def fps(ms):
                return _f(1e3 / ms if ms else None, ".3g")

            L += ["| | ms per future frame | fps | max err vs MuJoCo < 5 cm (mm) |", "|---|---|---|---|",
                  f"| ours (certified tolerance {cr.get('tolerance', '')}) | "
                  f"{_f(cr.get('contact_ms_per_frame_cpu'), '.1f')} | "
                  f"{_f(cr.get('contact_fps_cpu'), '.2f')} | {_f(cr.get('contact_err_max_mm_under_5cm'), '.2f')} |",
                  f"| ours, exact per pixel | {_f(cr.get('contact_exact_ms_per_frame_cpu'), '.1f')} | "
                  f"{fps(cr.get('contact_exact_ms_per_frame_cpu'))} | |",
                  f"| reference | {_f(cr.get('reference_ms_per_frame_cpu'), '.0f')} | "
                  f"{fps(cr.get('reference_ms_per_frame_cpu'))} | "
                  f"{_f(cr.get('reference_err_max_mm_under_5cm'), '.2f')} |"]
            if cr.get("reference_default_trees_ms_per_frame_cpu"):
                L.append(f"| reference, scipy's default balanced trees | "
                         f"{_f(cr['reference_default_trees_ms_per_frame_cpu'], '.0f')} | "
                         f"{fps(cr['reference_default_trees_ms_per_frame_cpu'])} | |")
            if cr.get("contact_ms_per_frame_cpu_mean_of_runs"):
                L.append(f"\nOurs: best of repeated runs per chunk (mean of runs "
                         f"{cr['contact_ms_per_frame_cpu_mean_of_runs']:.1f} ms/frame, CPU time "
                         f"{_f(cr.get('contact_cpu_time_ms_per_frame'), '.1f')} ms/frame).")
            L.append(f"\n{cr.get('future_frames_timed', '?')} future frames timed (reference on "
                     f"{w['contact_reference_frames'] or 'its default number of'} frames), "
                     f"{cr.get('oracle_samples_under_5cm', '?')} MuJoCo samples under 5 cm; ours / reference "
                     f"{_f(r['contact_ratio_vs_reference'], '.4f')} (reference / ours "
                     f"{_f(r['extra'].get('contact_speedup_vs_reference'), '.1f')}x).")
        d = r["depth_vs_lerobot_default"]
        L += ["", f"**Depth stream vs LeRobot's default encoder** ({d.get('episodes')} episode(s), {d.get('frames')} "
              f"view-frames at {small}, through `LeRobotDataset`; pixels with true depth in [0.1, 1.2] m)", "",
              "| encoder | median mm | p99 mm | max mm | KB per view-frame |", "|---|---|---|---|---|",
              f"| ours: x264rgb rgb24 qp0 gop10 | {_f(d.get('depth_err_median_mm'), '.2f')} | "
              f"{_f(d.get('depth_err_p99_mm'), '.2f')} | {_f(d.get('depth_err_max_mm'), '.1f')} | "
              f"{_f(d.get('kb_per_frame'), '.2f')} |",
              "| LeRobot default: svtav1 yuv420p crf30 gop2 | "
              f"{_f(d.get('depth_err_median_mm_lerobot_default'), '.2f')} | "
              f"{_f(d.get('depth_err_p99_mm_lerobot_default'), '.2f')} | "
              f"{_f(d.get('depth_err_max_mm_lerobot_default'), '.1f')} | "
              f"{_f(d.get('kb_per_frame_lerobot_default'), '.2f')} |"]
        if d.get("kb_per_frame") and d.get("kb_per_frame_lerobot_default"):
            L.append("\nSize ratio ours / LeRobot default: "
                     f"{d['kb_per_frame'] / d['kb_per_frame_lerobot_default']:.2f}x; "
                     f"p99 error ratio: {d['depth_err_p99_mm'] / d['depth_err_p99_mm_lerobot_default']:.4f}.")



    def _sections():
        nonlocal L
        L += ["", "## Sections", "", "| section | s | load at start | load at end |", "|---|---|---|---|"]
        for name, s in r["sections"].items():
            L.append(f"| {name} | {s['seconds']:.0f} | {s['load_avg_start']} | {s['load_avg_end']} |")

    def _errors():
        nonlocal L
        if r.get("errors"):
            L += ["", "## Failed parts (the run's exit status is 1)", ""]
            L += [f"* {k}: {v}" for k, v in r["errors"].items()]

    for part in (_headline, _whole_build, _against_baseline, _stages, _length, _output_bytes, _side_by_side, _errors, _sections):
        n = len(L)
        try:
            part()
        except Exception as e:  # noqa: BLE001  (a section of a partial result)
            del L[n:]
            L += ["", f"({part.__name__.strip('_')}: not available, {type(e).__name__}: {e})"]
    return "\n".join(L) + "\n"
