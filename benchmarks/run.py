"""The whole benchmark in one command: ``python -m benchmarks.run`` (``make bench``).

    python -m benchmarks.run [--quick] [--episodes N] [--long-frames N] [--baseline REV] [--out DIR] [--keep DIR]

Workload: scripted ``transfer_cube`` episodes recorded by :mod:`imac_data.sources.sim.recorder` (noise
0.3, seeds 0..), whole scripts (about 125 frames at 25 fps), three views, recorded depth,
at 240x320 and 480x640. One *frame* = 3 views x (base RGB + depth + motion + contact r2s +
contact s2g) plus the tabular columns.

1. **Whole builds**: ``imac_data.build.flow.build_dataset`` (what ``python -m imac_data.build`` runs),
   each in a fresh subprocess, end to end, at each size with 1 and 2 local workers, and
   with ``--executor ray`` and 2 workers. Frames/s; CPU seconds per frame (the build
   process and its pool workers by ``getrusage``; for Ray the workers' own CPU from the
   build's timings, which leave out Ray's own processes); peak RSS per worker (each worker's
   ``VmHWM``, from the build's timings); the load average at start and end.
2. **Stages**: the build's own stage timings (the side file every build writes to its
   staging directory, here passed out with ``--timings``), never a second copy of the
   pipeline: wall and CPU seconds per stage of the 1-worker build, and what stands between
   the result and 30 frames/s.
   With ``--baseline REV`` (``make bench``) the same episodes are also built by REV's command line
   and by ours, alternating (:mod:`benchmarks.same_host`): the ratio of one run on one machine.
3. **Episode length**: one 1000-frame episode at 480x640 and its first 100 frames,
   each built by one worker (synthetic: a recorded episode played forward and backward,
   ``imac_data.sources.hdf5.tile_episode``; recorded depth): peak RSS and frames/s.
4. **Side by side**, same process: our renderer vs MuJoCo's own OpenGL renderer and the
   mask IoU (``benchmarks/render_vs_mujoco.py``); our contact streams vs a straightforward
   trimesh-sampling + scipy KD-tree implementation, and their error against MuJoCo's
   ``mj_geomDistance`` (``benchmarks/contact_speed.py``); our depth stream vs LeRobot's
   default encoder through ``LeRobotDataset`` (``benchmarks/depth_fidelity.py``).

Writes ``latest.json`` (flat headline keys first, then the details) and ``latest.md`` into
``--out`` (default ``benchmarks/results/``). ``--quick`` is the CI smoke run
(``tests/test_benchmarks.py``): tiny resolutions, few frames, one build per kind; its
figures only show that the code runs. Timings are wall clock on a machine that may be
shared: the load average is recorded beside every build, and CPU seconds with it.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime as _dt
import inspect
import json
import math
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.run_report import markdown, tag
from benchmarks.workload import (
    REPO,
    RESULTS,
    TASK,
    VIEWS,
    Workload,
    commit,
    load_avg,
    log,
    machine,
    record,
    tree_bytes,
    versions,
    write_recipe,
)

# The keys every latest.json has (numbers measured in that run; None + a reason in
# ``not_measured`` when a workload cannot produce one, e.g. --quick never gets a gripper
# within 5 cm of the cube).
REQUIRED_STRINGS = ("machine", "commit")
TARGET_FPS = 30.0


# ----------------------------------------------------------------------------- 1. whole builds


def _usage_s() -> float:
    own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def child_build(spec_path: str) -> int:
    """Subprocess side of a whole build: ``build()`` timed end to end, its CPU, its timings."""
    spec = json.loads(Path(spec_path).read_text())
    from imac_data.build.flow import build_dataset as build
    from imac_data.build.staging import BuildRequest
    from imac_data.build.workers import peak_rss_mb
    from imac_data.console import quiet_libraries
    from imac_data.recipes import load_recipe

    quiet_libraries()
    root = Path(spec["root"])
    timings = Path(spec["result"]).with_suffix(".timings.json")
    req = BuildRequest(repo_id=spec["repo"], recipe=load_recipe(spec["recipe"]), root=root,
                       source_path=Path(spec["source"]), episodes=spec["episodes"], overwrite=True, progress=False,
                       timings=timings)
    load_start = load_avg()
    cpu0, t = _usage_s(), time.perf_counter()
    dataset = build(req, executor=spec["executor"], workers=spec["workers"])
    seconds, cpu = time.perf_counter() - t, _usage_s() - cpu0
    if spec["executor"] == "ray":
        import ray

        ray.shutdown()
    report = json.loads(timings.read_text())
    shards = report["episodes"]
    worker_cpu = sum(e["shard_cpu_s"] for e in shards) if spec["executor"] == "ray" else 0.0
    result = {
        "build_s": seconds, "cpu_s": cpu + worker_cpu, "frames": int(dataset.meta.total_frames),
        "episodes": int(dataset.meta.total_episodes), "load_avg_start": load_start, "load_avg_end": load_avg(),
        "rss_coordinator_mb": peak_rss_mb(),
        "peak_rss_mb_per_worker": max(e["peak_rss_mb"] for e in shards),
        "threads": report["threads"], "timings": report, "bytes": tree_bytes(root),
    }
    Path(spec["result"]).write_text(json.dumps(result))
    return 0


def whole_build(size, workers: int, executor: str, episodes: int, recipe: Path, source: Path, tmp: Path,
                name: str | None = None) -> dict:
    name = name or f"{tag(size)}_{executor}_w{workers}_e{episodes}"
    spec = {"repo": f"local/bench_{tag(size)}", "recipe": str(recipe), "source": str(source),
            "root": str(tmp / f"out_{name}"), "episodes": episodes, "workers": workers, "executor": executor,
            "result": str(tmp / f"build_{name}.json")}
    spec_path = tmp / f"build_{name}.spec.json"
    spec_path.write_text(json.dumps(spec))
    t = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "benchmarks.run", "--child-build", str(spec_path)], cwd=REPO,
                          capture_output=True, text=True)
    wall = time.perf_counter() - t
    if proc.returncode != 0:
        raise RuntimeError(f"build {name} failed (exit {proc.returncode}):\n{proc.stderr[-4000:]}")
    r = json.loads(Path(spec["result"]).read_text())
    shutil.rmtree(spec["root"], ignore_errors=True)
    return {"size": list(size), "workers": workers, "executor": executor, "threads": r["threads"],
            "episodes": r["episodes"], "frames": r["frames"], "build_s": r["build_s"], "fps": r["frames"] / r["build_s"],
            "cpu_s": r["cpu_s"], "cpu_ms_per_frame": 1e3 * r["cpu_s"] / r["frames"], "cli_wall_s": wall,
            "peak_mem_mb_per_worker": r["peak_rss_mb_per_worker"], "peak_mem_mb_coordinator": r["rss_coordinator_mb"],
            "bytes": r["bytes"], "bytes_per_frame": {k: v / r["frames"] for k, v in r["bytes"].items()},
            "load_avg_start": r["load_avg_start"], "load_avg_end": r["load_avg_end"], "timings": r["timings"]}


# ----------------------------------------------------------------------------- 2. stages


def stage_table(b: dict) -> dict:
    """Per stage of one build, from its own timings: wall and CPU ms per frame, share of the
    build's CPU; ``other`` = what the stages do not cover."""
    t = b["timings"]
    frames = b["frames"]
    wall, cpu = t["stages"]["wall_s"], t["stages"]["cpu_s"]
    rows = {k: {"wall_ms_per_frame": 1e3 * wall[k] / frames, "cpu_ms_per_frame": 1e3 * cpu.get(k, 0.0) / frames}
            for k in wall}
    staged_cpu = sum(cpu.values())
    rows["other"] = {"wall_ms_per_frame": max(1e3 * b["build_s"] / frames - sum(wall.values()) * 1e3 / frames
                                              / b["workers"], 0.0),
                     "cpu_ms_per_frame": max(1e3 * (b["cpu_s"] - staged_cpu) / frames, 0.0)}
    total = sum(r["cpu_ms_per_frame"] for r in rows.values())
    for r in rows.values():
        r["cpu_share"] = r["cpu_ms_per_frame"] / total if total else None
    return {"size": b["size"], "workers": b["workers"], "threads": b["threads"], "frames": frames, "rows": rows,
            "cpu_ms_per_frame": total, "fps": b["fps"]}


def gap_to_target(table: dict, cores: int, target: float = TARGET_FPS) -> dict:
    """What stands between a build and ``target`` frames/s on ``cores`` cores: the CPU
    budget per frame and each stage's CPU against it."""
    budget = 1e3 * cores / target
    rows = sorted(table["rows"].items(), key=lambda kv: -kv[1]["cpu_ms_per_frame"])
    return {"target_fps": target, "cores": cores, "budget_cpu_ms_per_frame": budget,
            "cpu_ms_per_frame": table["cpu_ms_per_frame"], "over_budget_x": table["cpu_ms_per_frame"] / budget,
            "largest": [(k, v["cpu_ms_per_frame"]) for k, v in rows[:4]]}


# ----------------------------------------------------------------------------- 3. episode length


def long_episodes(work: Workload, source: Path, recipe: Path, tmp: Path) -> dict:
    """One worker builds a ``long_frames`` and a ``short_frames`` episode (tiles of a recorded one)."""
    from imac_data.sources.hdf5 import tile_episode

    rows = {}
    for n in (work.short_frames, work.long_frames):
        d = tmp / f"tiled_{n}"
        d.mkdir(exist_ok=True)
        shutil.copy(source / "calibration.json", d / "calibration.json")
        tile_episode(source / "episode_0.hdf5", d / "episode_0.hdf5", n)
        b = whole_build(work.long_size, 1, "local", 1, recipe, d, tmp, name=f"tiled_{n}")
        rows[str(n)] = {k: b[k] for k in ("frames", "build_s", "fps", "cpu_ms_per_frame", "peak_mem_mb_per_worker",
                                          "load_avg_start", "load_avg_end")}
        rows[str(n)]["stages"] = stage_table(b)
        shutil.rmtree(d, ignore_errors=True)
    short, long_ = rows[str(work.short_frames)], rows[str(work.long_frames)]
    return {"size": list(work.long_size), "rows": rows,
            "peak_ratio_long_vs_short": long_["peak_mem_mb_per_worker"] / short["peak_mem_mb_per_worker"]}


# ----------------------------------------------------------------------------- 4. side by side


def against_baseline(work: Workload, recipes: dict, sources: dict, tmp: Path) -> dict:
    """This checkout's CLI and ``work.baseline``'s on the run's own recorded episodes, one round per
    worker setting of the whole builds (:func:`benchmarks.same_host.compare`)."""
    from benchmarks import same_host  # it imports this module

    sizes = [s for s in work.sizes if not (work.quick and s != work.small)]
    return same_host.compare(work.baseline, [(s, recipes[s], sources[s], work.episodes_at(s)) for s in sizes],
                             work.workers, 1, tmp)


def _ratio(a, b):
    return a / b if isinstance(a, (int, float)) and isinstance(b, (int, float)) and b else None


def _call(fn, **kwargs):
    """Call a sibling benchmark's ``run`` with the keyword arguments it accepts (they are
    written by others and their signatures may change); returns (result, ignored kwargs)."""
    params = inspect.signature(fn).parameters
    if any(p.kind == p.VAR_KEYWORD for p in params.values()):
        return fn(**kwargs), []
    return fn(**{k: v for k, v in kwargs.items() if k in params}), sorted(set(kwargs) - set(params))


@contextlib.contextmanager
def _restore_process_state():
    """contact_speed pins CPU affinity and torch threads; undo that afterwards."""
    import torch

    threads = torch.get_num_threads()
    affinity = os.sched_getaffinity(0) if hasattr(os, "sched_getaffinity") else None
    try:
        yield
    finally:
        torch.set_num_threads(threads)
        if affinity is not None:
            with contextlib.suppress(OSError):
                os.sched_setaffinity(0, affinity)


def render_comparison(work: Workload, sources: dict) -> dict:
    from benchmarks import render_vs_mujoco as rvm

    if not work.quick:
        r, ignored = _call(rvm.run, quick=False, episodes=work.render_episodes, seed=work.seed,
                           timing_frames=work.render_frames, verbose=False)
        out = {k: v for k, v in r.items() if isinstance(v, (int, float))}
        out["accuracy"] = r.get("accuracy")
        out["timing_ms_per_view"] = r.get("timing_ms_per_view")
        out["how"] = ("render_vs_mujoco.run: mask IoU over whole scripted episodes of both tasks vs MuJoCo's "
                      "robot-only segmentation; speed in interleaved blocks")
        out["ignored_args"] = ignored
        return out
    return _render_quick(work, sources, rvm)


def _render_quick(work: Workload, sources: dict, rvm) -> dict:
    """--quick: render_vs_mujoco's oracle and timing at the tiny sizes on the workload's frames."""
    import numpy as np
    import torch

    from imac_data.core.render import RaycastRenderer
    from imac_data.core.robot import aloha
    from imac_data.core.robot.model import RobotModel
    from imac_data.sources.hdf5 import episode_paths, read_episode
    from imac_data.sources.sim import rig as sim_rig

    robot = RobotModel(aloha.robot_config())
    h, w = work.small
    q = np.concatenate([read_episode(p, load_depth=False).qpos for p in episode_paths(sources[work.small])])
    oracle = rvm.MujocoViews(TASK, h, w, robot_only=True)
    iou = {c: [] for c in VIEWS}
    try:
        calib = sim_rig.camera_calibration(oracle.model, w, h)
        views = RaycastRenderer(robot, near=oracle.near).render(torch.as_tensor(q), calib)
        for j in range(len(q)):
            ref = oracle.robot_mask_depth(q[j])
            for c in VIEWS:
                mask, truth = views[c].mask[j].numpy(), ref[c][0]
                union = (mask | truth).sum()
                if union:
                    iou[c].append((mask & truth).sum() / union)
    finally:
        oracle.close()
    batch = max(1, min(4, len(q)))
    times = {tag(size): rvm.timing(robot, TASK, q, size[0], size[1], batch, shipped_frames=1) for size in work.sizes}
    t0, t1 = times[tag(work.sizes[0])], times[tag(work.sizes[-1])]
    return {
        "render_ms_per_view_240": t0["ours_batch"], "render_ms_per_view_480": t1["ours_batch"],
        "render_ratio_vs_mujoco": t0["ours_batch"] / t0["mj_rgb"],
        "render_ratio_vs_mujoco_480": t1["ours_batch"] / t1["mj_rgb"],
        "render_ratio_vs_mujoco_all_passes": t0["ours_batch"] / (t0["mj_rgb"] + t0["mj_depth"] + t0["mj_seg"]),
        "mujoco_rgb_ms_per_view_240": t0["mj_rgb"],
        "mask_iou_head": float(np.mean(iou["cam_high"])),
        "mask_iou_wrist_min": float(min(np.mean(iou[c]) for c in VIEWS[1:])),
        "timing_ms_per_view": times,
        "how": f"--quick: IoU on the {len(q)} workload frames at {tag(work.small)}; render_vs_mujoco.timing",
    }


def contact_comparison(work: Workload) -> dict:
    try:
        from benchmarks import contact_speed
    except ImportError as e:
        return {"error": f"benchmarks.contact_speed not importable: {e}"}
    kwargs = {"quick": work.quick, "cores": 2, "seed": work.seed}
    if work.contact_steps is not None:
        kwargs["max_steps"] = work.contact_steps
    if work.contact_reference_frames is not None:
        kwargs["reference_frames"] = work.contact_reference_frames
    with _restore_process_state():
        r, ignored = _call(contact_speed.run, **kwargs)
    out = dict(r)
    if "contact_ratio_vs_reference" in out:  # contact_speed's own ratio is reference / ours
        out["speedup_vs_reference_as_contact_speed_reports"] = out.pop("contact_ratio_vs_reference")
    out["ignored_args"] = ignored
    return out


def depth_comparison(work: Workload) -> dict:
    from benchmarks import depth_fidelity

    h, w = work.small
    r, ignored = _call(depth_fidelity.run, episodes=work.depth_episodes, width=w, height=h,
                       max_steps=work.depth_max_steps, with_candidates=False)
    out = {k: v for k, v in r.items() if k != "candidates"}
    out["ignored_args"] = ignored
    return out


# ----------------------------------------------------------------------------- run


# ----------------------------------------------------------------------------- run


def run(work: Workload, tmp: Path) -> dict:
    started = _dt.datetime.now(_dt.timezone.utc)
    t_start = time.perf_counter()
    head, dirty = commit()
    res = {"load_avg_start": load_avg()}
    sections: dict[str, dict] = {}
    errors: dict[str, str] = {}

    def section(name):
        sections[name] = {"load_avg_start": load_avg(), "t0": time.perf_counter()}
        log(f"{name} ...")

    def done(name):
        s = sections[name]
        s["seconds"] = time.perf_counter() - s.pop("t0")
        s["load_avg_end"] = load_avg()
        log(f"{name}: {s['seconds']:.0f} s")

    def attempt(what: str, fn, default=None):
        """A failing part is recorded (``errors``, exit status 1) and the run goes on."""
        try:
            return fn()
        except Exception as e:  # noqa: BLE001  (recorded, reported, and the exit status says so)
            import traceback

            errors[what] = f"{type(e).__name__}: {e}"[:2000]
            log(f"FAILED {what}:\n{traceback.format_exc()[-3000:]}")
            return default

    section("record")
    recipes, sources, record_s = {}, {}, {}
    for size in dict.fromkeys([*work.sizes, work.long_size]):
        recipes[size] = write_recipe(tmp / f"recipe_{tag(size)}.yaml", size, work.episodes_at(size), work.seed,
                                     work.noise)
        sources[size] = tmp / f"src_{tag(size)}"
        record_s[tag(size)] = record(work, size, sources[size])
    done("record")

    section("builds")
    builds = []
    for size, workers, executor in work.builds():
        log(f"  build {tag(size)}, {work.episodes_at(size)} episodes, {workers} worker(s), {executor}")
        b = attempt(f"build {tag(size)} {executor} w{workers}",
                    lambda: whole_build(size, workers, executor, work.episodes_at(size), recipes[size], sources[size],
                                        tmp))
        if b is not None:
            builds.append(b)
            log(f"    {b['frames']} frames in {b['build_s']:.1f} s = {b['fps']:.2f} fps, {b['cpu_ms_per_frame']:.0f} "
                f"CPU ms/frame, peak {b['peak_mem_mb_per_worker']:.0f} MB per worker, load {b['load_avg_end'][0]}")
    done("builds")

    same_host = {}
    if work.baseline:
        section("same_host")
        same_host = attempt(f"same_host {work.baseline}", lambda: against_baseline(work, recipes, sources, tmp), {})
        done("same_host")

    section("episode_length")
    length = attempt("episode_length", lambda: long_episodes(work, sources[work.long_size], recipes[work.long_size],
                                                             tmp), {})
    done("episode_length")

    section("render_vs_mujoco")
    render = attempt("render_vs_mujoco", lambda: render_comparison(work, sources), {})
    done("render_vs_mujoco")
    section("contact_speed")
    contact = attempt("contact_speed", lambda: contact_comparison(work), {})
    done("contact_speed")
    section("depth_fidelity")
    depth = attempt("depth_fidelity", lambda: depth_comparison(work), {})
    done("depth_fidelity")

    def build_of(size, workers, executor="local"):
        for b in builds:
            if tuple(b["size"]) == tuple(size) and b["workers"] == workers and b["executor"] == executor:
                return b
        return None

    def best(size):
        local = [b for b in builds if tuple(b["size"]) == tuple(size) and b["executor"] == "local"]
        return max(local, key=lambda b: b["fps"]) if local else None

    small, large = work.sizes[0], work.sizes[-1]
    stages = {tag(size): stage_table(build_of(size, 1)) for size in work.sizes if build_of(size, 1)}
    gap = {k: gap_to_target(v, os.cpu_count() or 1) for k, v in stages.items()}
    b_small, b_large, b_ray = best(small), best(large), build_of(small, work.ray_workers, "ray")
    rows = (length or {}).get("rows", {})
    flat = {
        "fps_total_240": (b_small or {}).get("fps"),
        "cpu_ms_per_frame_240": (b_small or {}).get("cpu_ms_per_frame"),
        "peak_mem_mb_per_worker": (b_small or {}).get("peak_mem_mb_per_worker"),
        "fps_total_480": (b_large or {}).get("fps") if not work.quick else (b_small or {}).get("fps"),
        "cpu_ms_per_frame_480": (b_large or {}).get("cpu_ms_per_frame") if not work.quick
        else (b_small or {}).get("cpu_ms_per_frame"),
        "fps_ray_240": (b_ray or {}).get("fps"),
        "long_episode_peak_mb": rows.get(str(work.long_frames), {}).get("peak_mem_mb_per_worker"),
        "short_episode_peak_mb": rows.get(str(work.short_frames), {}).get("peak_mem_mb_per_worker"),
        "long_episode_fps": rows.get(str(work.long_frames), {}).get("fps"),
        "render_ms_per_view_240": render.get("render_ms_per_view_240"),
        "render_ratio_vs_mujoco": render.get("render_ratio_vs_mujoco"),
        "contact_fps_cpu": contact.get("contact_fps_cpu"),
        "contact_ratio_vs_reference": _ratio(contact.get("contact_ms_per_frame_cpu"),
                                             contact.get("reference_ms_per_frame_cpu")),
        "depth_err_median_mm": depth.get("depth_err_median_mm"),
        "depth_err_p99_mm": depth.get("depth_err_p99_mm"),
        "depth_err_p99_mm_lerobot_default": depth.get("depth_err_p99_mm_lerobot_default"),
        "mask_iou_head": render.get("mask_iou_head"),
        "mask_iou_wrist_min": render.get("mask_iou_wrist_min"),
        "contact_err_max_mm_under_5cm": contact.get("contact_err_max_mm_under_5cm"),
    }
    extra = {}
    for b in builds:
        extra[f"fps_{b['size'][0]}_{b['executor']}_w{b['workers']}"] = b["fps"]
        extra[f"cpu_ms_per_frame_{b['size'][0]}_{b['executor']}_w{b['workers']}"] = b["cpu_ms_per_frame"]
        extra[f"peak_mem_mb_per_worker_{b['size'][0]}_{b['executor']}_w{b['workers']}"] = b["peak_mem_mb_per_worker"]
    for k in ("render_ms_per_view_480", "render_ratio_vs_mujoco_480", "render_ratio_vs_mujoco_all_passes"):
        extra[k] = render.get(k)
    for k in ("contact_ms_per_frame_cpu", "reference_ms_per_frame_cpu", "reference_err_max_mm_under_5cm",
              "contact_exact_ms_per_frame_cpu", "reference_default_trees_ms_per_frame_cpu"):
        extra[k] = contact.get(k)
    extra["contact_speedup_vs_reference"] = _ratio(contact.get("reference_ms_per_frame_cpu"),
                                                   contact.get("contact_ms_per_frame_cpu"))
    for k in ("kb_per_frame", "kb_per_frame_lerobot_default", "depth_err_max_mm", "depth_err_max_mm_lerobot_default",
              "depth_err_median_mm_lerobot_default"):
        extra[f"depth_{k}" if not k.startswith("depth") else k] = depth.get(k)

    not_measured = {}
    for k, v in flat.items():
        if not isinstance(v, (int, float)) or not math.isfinite(v):
            why = {"contact_err_max_mm_under_5cm": "the contact_speed episode never brought a finger within 5 cm "
                                                   "of the cube (too few steps)"}.get(k, "not returned")
            if errors:
                why += f" (failed parts: {', '.join(errors)})"
            not_measured[k] = why
    for b in builds:
        b.pop("timings", None)  # summarised in "stages"
    res.update({
        **flat,
        "machine": machine(),
        "commit": head,
        "commit_dirty_files": dirty,
        "load_avg": {"start": res.pop("load_avg_start"), "end": load_avg(),
                     "note": "1/5/15-minute load averages; the machine may be shared, timings are wall clock"},
        "not_measured": not_measured,
        "errors": errors,
        "quick": work.quick,
        "date": started.isoformat(timespec="seconds"),
        "seconds": time.perf_counter() - t_start,
        "workload": {**{k: v for k, v in work.__dict__.items()}, "task": TASK, "views": list(VIEWS),
                     "frames_per_episode": (builds[0]["frames"] / builds[0]["episodes"] if builds else None),
                     "key_sizes": {"_240": tag(small), "_480": tag(large)}, "record_s": record_s},
        "versions": versions(),
        "extra": extra,
        "builds": builds,
        "stages": stages,
        "gap_to_30fps": gap,
        "same_host": same_host,
        "episode_length": length,
        "render_vs_mujoco": render,
        "contact_vs_reference": contact,
        "depth_vs_lerobot_default": depth,
        "sections": sections,
    })
    return res


# ----------------------------------------------------------------------------- output


def _clean(x):
    """JSON-safe: non-finite floats -> None, tuples -> lists, numpy scalars -> Python."""
    if isinstance(x, dict):
        return {str(k): _clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_clean(v) for v in x]
    if hasattr(x, "item") and not isinstance(x, (str, bytes)):
        with contextlib.suppress(Exception):
            x = x.item()
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, (str, int, float, bool)) or x is None:
        return x
    return str(x)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.run", description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="CI smoke run: tiny sizes, few frames (figures not meaningful)")
    p.add_argument("--episodes", type=int, help="episodes in the workload (default 4)")
    p.add_argument("--max-steps", type=int, help="50 Hz steps per episode (default: the whole script)")
    p.add_argument("--long-frames", type=int, help="frames of the long episode (default 1000)")
    p.add_argument("--no-ray", action="store_true", help="skip the Ray build")
    p.add_argument("--baseline", help="also build the same episodes with this revision's CLI and report the ratio "
                                      "(make bench: the revision issue 65 started from)")
    p.add_argument("--render-frames", type=int, help="render_vs_mujoco timing frames per size (default 32)")
    p.add_argument("--contact-reference-frames", type=int, help="frames the slow contact reference runs on (default 8)")
    p.add_argument("--out", type=Path, default=RESULTS, help="where latest.json / latest.md go (default %(default)s)")
    p.add_argument("--keep", type=Path, help="work in this directory and keep it (default: a temporary one)")
    p.add_argument("--from-json", type=Path, help="only re-render latest.md (into --out) from this latest.json")
    p.add_argument("--child-build", help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    if a.child_build:
        return child_build(a.child_build)
    if a.from_json:
        a.out.mkdir(parents=True, exist_ok=True)
        (a.out / "latest.md").write_text(markdown(json.loads(a.from_json.read_text())))
        return 0
    work = Workload.quick_default() if a.quick else Workload()
    for flag, attr in (("episodes", "episodes"), ("max_steps", "max_steps"), ("render_frames", "render_frames"),
                       ("contact_reference_frames", "contact_reference_frames"), ("long_frames", "long_frames")):
        if getattr(a, flag) is not None:
            setattr(work, attr, getattr(a, flag))
    if a.no_ray:
        work.ray_workers = 0
    work.baseline = a.baseline
    if work.episodes < 1 or (work.max_steps is not None and work.max_steps < 2):
        p.error("--episodes must be >= 1 and --max-steps >= 2")

    from imac_data.console import quiet_libraries

    quiet_libraries()
    tmp = a.keep or Path(tempfile.mkdtemp(prefix="imac_bench_"))
    tmp.mkdir(parents=True, exist_ok=True)
    try:
        result = _clean(run(work, tmp))
    finally:
        if not a.keep:
            shutil.rmtree(tmp, ignore_errors=True)
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / "latest.json").write_text(json.dumps(result, indent=1) + "\n")
    text = markdown(result)
    (a.out / "latest.md").write_text(text)
    print(text)
    print(f"wrote {a.out / 'latest.json'} and {a.out / 'latest.md'}", file=sys.stderr)
    if result["errors"]:
        print(f"FAILED parts: {', '.join(result['errors'])}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
