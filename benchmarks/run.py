"""The whole benchmark in one command: ``python -m benchmarks.run`` (``make bench``).

    python -m benchmarks.run [--quick] [--episodes N] [--max-steps S] [--out DIR] [--keep DIR]

One fixed simulated workload (scripted ``transfer_cube`` episodes from
:mod:`imac_data.simulate`, noise 0.3, seeds 0.., the same episodes recorded at each
resolution; ``--episodes`` x ``--max-steps`` 50 Hz steps, i.e. ``max_steps / 2``
frames at 25 fps per episode), three views. One *frame* = all three views and all
added streams (motion, depth, contact r2s + s2g per view) plus the base dataset.

1. **Whole build** (``imac_data.build.build``, exactly what ``python -m
   imac_data.build`` runs: ingest + FK + render + depth + contact + video encode +
   write per episode shard, then aggregate, dataset card, validation) timed end to
   end at each resolution with 1 and 2 workers, each build in a fresh subprocess
   (``--child-build``) so its peak memory is its own: the coordinator's
   ``RUSAGE_SELF`` and the largest pool worker's ``RUSAGE_CHILDREN`` ``ru_maxrss``
   (with 1 worker the work runs in the coordinator). Also the build of 1 episode
   (1 worker) at the small size, for the fixed cost per build vs the cost per episode.
   Output bytes per frame per stream group, from the built datasets.
2. **Stages**, the functions the build calls, timed one by one in this process on the
   same episodes (1 process, torch's default threads): read (HDF5 + camera poses +
   depth), ingest (LeRobot base dataset: RGB encode, parquet, stats), FK (commanded
   configurations, link poses, camera poses, gripper samples), render (state and
   command, all views), depth (resize + colour codec), contact
   (``imac_data.contact.episode_contact``), video encode (``encode_video`` of the 9
   control and 3 depth streams, lossless RGB H.264 as the build writes them), write
   (``augment_dataset`` minus its depth and video encoding). ``other`` = the 1-worker
   build minus the sum of the stages (aggregation, dataset card, validation, LeRobot
   metadata loads). Cost versus views: render and contact on 1, 2, 3 views.
3. **Side by side**, same process: our renderer vs MuJoCo's own OpenGL renderer and the
   mask IoU (``benchmarks/render_vs_mujoco.py``); our contact builder vs a
   straightforward trimesh-sampling + scipy KD-tree implementation, and its error
   against MuJoCo's ``mj_geomDistance`` (``benchmarks/contact_speed.py``); our depth
   stream vs LeRobot's default encoder through ``LeRobotDataset``
   (``benchmarks/depth_fidelity.py``, without its candidate table).

Writes ``latest.json`` (flat headline keys first, then the details) and ``latest.md``
into ``--out`` (default ``benchmarks/results/``). ``--quick`` is the CI smoke run
(``tests/test_benchmarks.py``): tiny resolutions, few frames, one build per worker
count; its figures only show that the code runs. Timings are wall clock on a machine
that may be shared: ``load_avg`` records the load at start and end (and per section).
"""

from __future__ import annotations

import argparse
import contextlib
import datetime as _dt
import inspect
import json
import math
import os
import platform
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("SVT_LOG", "1")  # SVT-AV1 (LeRobot's encoder): errors only

REPO = Path(__file__).resolve().parent.parent
RESULTS = REPO / "benchmarks" / "results"
VIEWS = ("cam_high", "cam_left_wrist", "cam_right_wrist")  # DESIGN.md order: head, left, right wrist
TASK = "transfer_cube"

# The keys every latest.json has (numbers measured in that run; None + a reason in
# ``not_measured`` when a workload cannot produce one, e.g. --quick never gets a gripper
# within 5 cm of the cube).
REQUIRED_NUMBERS = (
    "fps_total_240", "peak_mem_mb_per_worker", "render_ms_per_view_240", "render_ratio_vs_mujoco",
    "contact_fps_cpu", "contact_ratio_vs_reference", "depth_err_median_mm", "depth_err_p99_mm",
    "depth_err_p99_mm_lerobot_default", "mask_iou_head", "mask_iou_wrist_min", "contact_err_max_mm_under_5cm",
)
REQUIRED_STRINGS = ("machine", "commit")

STAGES = ("setup", "read", "ingest", "fk", "render", "depth", "contact", "video_encode", "write", "aggregate",
          "validate")
STAGE_LABELS = {
    "setup": "setup per worker (robot model, renderer scene, controller, gripper samples)",
    "read": "decode/read (HDF5, camera poses, depth mm->m)",
    "ingest": "ingest (LeRobot base dataset: RGB svtav1 encode, parquet, stats)",
    "fk": "FK (commanded q, link poses, camera poses, gripper samples)",
    "render": "render (state + command, all views)",
    "depth": "depth encode (resize + colour codec)",
    "contact": "contact (both streams, caps, colour)",
    "video_encode": "video encode (9 control + 3 depth streams, x264rgb qp0)",
    "write": "write (augment_dataset minus its encoding: parquet, stats, metadata)",
    "aggregate": "aggregate the episode shards (LeRobot aggregate_datasets)",
    "validate": "load + validate the result (LeRobotDataset, sample decode)",
    "other": "other = 1-worker build - stages (process start-up, input checks, card, reloads, moves)",
}
STREAM_GROUPS = {
    "rgb (LeRobot encoder)": "observation.images.",
    "depth": "observation.depth.",
    "motion": "control.motion.",
    "contact_r2s": "control.contact_r2s.",
    "contact_s2g": "control.contact_s2g.",
}


@dataclass
class Workload:
    """What one run measures (the CLI flags)."""

    quick: bool = False
    sizes: tuple[tuple[int, int], ...] = ((240, 320), (480, 640))
    episodes: int = 2
    max_steps: int = 96  # 50 Hz control steps per episode -> max_steps / 2 frames at 25 fps
    workers: tuple[int, ...] = (1, 2)
    episode_scaling: bool = True  # also build 1 episode (1 worker, small size)
    view_frames: int = 17  # frames for the cost-vs-views run (2 contact chunks of 8 + frame 0)
    render_episodes: int = 1  # render_vs_mujoco: scripted episodes per task (accuracy)
    render_frames: int = 32  # render_vs_mujoco: timing frames per size
    contact_steps: int | None = None  # contact_speed: 50 Hz steps (None: its default)
    contact_reference_frames: int | None = 8
    depth_episodes: int = 1
    depth_max_steps: int | None = 120
    seed: int = 0
    noise: float = 0.3

    @classmethod
    def quick_default(cls) -> Workload:
        return cls(quick=True, sizes=((48, 64), (96, 128)), episodes=2, max_steps=8, workers=(2,),
                   episode_scaling=False, view_frames=5, render_frames=4, contact_steps=16,
                   contact_reference_frames=1, depth_max_steps=8)

    @property
    def small(self) -> tuple[int, int]:
        return self.sizes[0]

    def builds(self) -> list[tuple[tuple[int, int], int, int]]:
        """(size, workers, episodes) of every whole build, in run order."""
        plan = []
        for size in self.sizes:
            if self.quick and size != self.small:
                continue  # --quick: one whole build (small size, 2 workers: the pool path)
            plan += [(size, w, self.episodes) for w in self.workers]
        if self.episode_scaling and self.episodes > 1:
            plan.append((self.small, 1, 1))
        return plan


def tag(size) -> str:
    return f"{size[0]}x{size[1]}"


# ----------------------------------------------------------------------------- environment


def machine() -> str:
    model = platform.processor() or platform.machine()
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    mem = ""
    with contextlib.suppress(OSError, ValueError, IndexError):
        kb = int(Path("/proc/meminfo").read_text().split("MemTotal:")[1].split()[0])
        mem = f", {kb / 2**20:.0f} GiB RAM"
    return (f"{os.cpu_count()} cores, {model}{mem}, {platform.system()} {platform.machine()}, "
            f"Python {platform.python_version()}")


def commit() -> tuple[str, list[str]]:
    """HEAD and the tracked files that differ from it (read-only git: no index refresh)."""
    def git(*args):
        return subprocess.run(["git", "--no-optional-locks", *args], cwd=REPO, capture_output=True, text=True,
                              timeout=30).stdout
    try:
        head = git("rev-parse", "HEAD").strip() or "unknown"
        dirty = [line[3:] for line in git("status", "--porcelain", "--untracked-files=no").splitlines() if line]
    except (OSError, subprocess.SubprocessError):
        head, dirty = "unknown", []
    return head, dirty


def versions() -> dict:
    from importlib.metadata import PackageNotFoundError, version

    out = {}
    for pkg in ("torch", "numpy", "open3d", "mujoco", "lerobot", "av", "scipy", "trimesh"):
        try:
            out[pkg] = version(pkg)
        except PackageNotFoundError:
            out[pkg] = None
    return out


def load_avg() -> list[float]:
    return [round(x, 2) for x in os.getloadavg()]


class Timer:
    """Accumulating stopwatch per key."""

    def __init__(self):
        self.s: dict[str, float] = defaultdict(float)

    @contextlib.contextmanager
    def __call__(self, key: str):
        t = time.perf_counter()
        try:
            yield
        finally:
            self.s[key] += time.perf_counter() - t


class PeakRSS:
    """Peak resident memory of this process while the block runs, sampled every 20 ms
    (Linux ``/proc/self/statm``); ``peak_mb`` - ``start_mb`` = the block's working set."""

    def __init__(self):
        self.start_mb = self.peak_mb = None

    @staticmethod
    def now_mb() -> float | None:
        try:
            return int(Path("/proc/self/statm").read_text().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
        except (OSError, ValueError, IndexError):
            return None

    def __enter__(self):
        import threading

        self.start_mb = self.peak_mb = self.now_mb()
        self._stop = threading.Event()

        def sample():
            while not self._stop.wait(0.02):
                v = self.now_mb()
                if v is not None and (self.peak_mb is None or v > self.peak_mb):
                    self.peak_mb = v

        self._thread = threading.Thread(target=sample, daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()

    @property
    def delta_mb(self) -> float | None:
        return None if self.start_mb is None else self.peak_mb - self.start_mb


def log(msg: str) -> None:
    print(f"[bench {time.strftime('%H:%M:%S')} load {os.getloadavg()[0]:.1f}] {msg}", file=sys.stderr, flush=True)


# ----------------------------------------------------------------------------- workload


def write_recipe(path: Path, size, episodes: int, seed: int, noise: float) -> Path:
    """The shipped transfer-cube recipe at ``size`` (recorded and augmented)."""
    import yaml

    from imac_data.recipes import RECIPES_DIR

    data = yaml.safe_load((RECIPES_DIR / "aloha_sim_transfer_cube.yaml").read_text())
    data["name"] = f"bench_{tag(size)}"
    data["source"]["episodes"] = episodes
    data["source"]["sim"].update(height=size[0], width=size[1], seed=seed, noise=noise)
    data.setdefault("augment", {}).update(height=size[0], width=size[1])
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def record(work: Workload, size, out: Path) -> float:
    from imac_data.simulate import SimConfig, record_dataset

    t = time.perf_counter()
    record_dataset(SimConfig(task=TASK, num_episodes=work.episodes, height=size[0], width=size[1], seed=work.seed,
                             noise=work.noise, max_steps=work.max_steps), out, progress=False, overwrite=True)
    return time.perf_counter() - t


def tree_bytes(root: Path) -> dict:
    """Bytes of a dataset: total, per stream group (videos/<key>/), tabular (data + meta)."""
    out = {"total": 0, "tabular": 0, **{g: 0 for g in STREAM_GROUPS}}
    for f in root.rglob("*"):
        if not f.is_file():
            continue
        n = f.stat().st_size
        out["total"] += n
        rel = f.relative_to(root).parts
        if rel[0] == "videos" and len(rel) > 1:
            for group, prefix in STREAM_GROUPS.items():
                if rel[1].startswith(prefix):
                    out[group] += n
        elif rel[0] in ("data", "meta"):
            out["tabular"] += n
    return out


# ----------------------------------------------------------------------------- 1. whole builds


def child_build(spec_path: str) -> int:
    """Subprocess side of a whole build: ``build()`` timed end to end, then peak RSS."""
    spec = json.loads(Path(spec_path).read_text())
    from imac_data.build import BuildRequest, build
    from imac_data.cli import quiet_libraries
    from imac_data.recipes import load_recipe

    quiet_libraries()
    root = Path(spec["root"])
    req = BuildRequest(repo_id=spec["repo"], recipe=load_recipe(spec["recipe"]), root=root,
                       source_path=Path(spec["source"]), episodes=spec["episodes"], overwrite=True, progress=False)
    t = time.perf_counter()
    dataset = build(req, workers=spec["workers"])
    seconds = time.perf_counter() - t
    result = {
        "build_s": seconds,
        "frames": int(dataset.meta.total_frames),
        "episodes": int(dataset.meta.total_episodes),
        "rss_self_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "rss_children_mb": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024,
        "bytes": tree_bytes(root),
    }
    Path(spec["result"]).write_text(json.dumps(result))
    return 0


def whole_build(work: Workload, size, workers: int, episodes: int, recipe: Path, source: Path, tmp: Path) -> dict:
    name = f"{tag(size)}_w{workers}_e{episodes}"
    spec = {"repo": f"local/bench_{tag(size)}", "recipe": str(recipe), "source": str(source),
            "root": str(tmp / f"out_{name}"), "episodes": episodes, "workers": workers,
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
    per_worker = r["rss_children_mb"] if workers > 1 and episodes > 1 else r["rss_self_mb"]
    return {"size": list(size), "workers": workers, "episodes": r["episodes"], "frames": r["frames"],
            "build_s": r["build_s"], "fps": r["frames"] / r["build_s"], "cli_wall_s": wall,
            "peak_mem_mb_per_worker": per_worker, "peak_mem_mb_coordinator": r["rss_self_mb"],
            "bytes": r["bytes"], "bytes_per_frame": {k: v / r["frames"] for k, v in r["bytes"].items()},
            "load_avg_end": load_avg()}


# ----------------------------------------------------------------------------- 2. stages


class Pipeline:
    """What a build worker holds (built once per size, like ``build._process_state``)."""

    def __init__(self, recipe_path: Path, source: Path):
        from imac_data.recipes import load_recipe
        from imac_data.rig import Rig

        t = time.perf_counter()  # imports excluded (a worker pays them once, before its first episode)
        self.recipe = load_recipe(recipe_path)
        self.settings = self.recipe.augment
        self.rig = Rig.from_recipe(self.recipe, source / "calibration.json")
        self.robot = self.rig.robot
        self.renderer = self.rig.renderer
        self.controller = self.rig.controller
        self.gripper = self.rig.gripper
        self.source = source
        self.calibration = self.rig.cameras
        self.setup_s = time.perf_counter() - t
        import lerobot.datasets.aggregate  # noqa: F401  (imports outside the timed stages)
        import lerobot.datasets.compute_stats  # noqa: F401
        import lerobot.datasets.lerobot_dataset  # noqa: F401

    def ingest_options(self, fps: float):
        from imac_data.aloha import STATE_NAMES
        from imac_data.ingest import IngestOptions

        d = self.recipe.source.episode_defaults
        return IngestOptions(fps=fps, task=self.recipe.task, source=d.source, policy_name=d.policy_name,
                             checkpoint=d.checkpoint, robot_type=self.robot.name, state_names=STATE_NAMES)


def episode_stages(pipe: Pipeline, path: Path, tmp: Path, timer: Timer, *, cameras=VIEWS, frames: int | None = None,
                   full: bool = True, shard: Path | None = None) -> int:
    """One episode through the build's stage functions (as ``build_shard`` /
    ``augment.episode_streams`` / ``augment.augment_dataset`` call them), each timed.
    ``full=False``: FK, render and contact only (the cost-vs-views runs). The one-episode
    dataset (base + streams) is left at ``shard`` (default: deleted). Returns T."""
    import numpy as np
    import torch

    from imac_data.aloha_hdf5 import read_episode
    from imac_data.augment import MOTION, R2S, S2G, EpisodeStreams, augment_dataset
    from imac_data.contact import episode_contact
    from imac_data.depth import DepthCodec, depth_stream_key, resize_depth
    from imac_data.depth_sources import RecordedDepth, episode_views
    from imac_data.ingest import ingest_episodes
    from imac_data.motion import frame_configurations
    from imac_data.dataset.videos import VideoEncoding, encode_video

    s, robot, renderer = pipe.settings, pipe.robot, pipe.renderer
    H, W = s.resolution
    with timer("read"):
        raw = read_episode(path)
        views = episode_views(raw, pipe.calibration, robot, name=str(path))
        source = RecordedDepth()
        depth = source.depth(views)
    fps = raw.fps or pipe.recipe.fps or 25
    root = shard or tmp / "stage_dataset"
    if full:
        with timer("ingest"):
            ingest_episodes([path], rig=pipe.rig, repo_id="local/bench_stage",
                            root=root, options=pipe.ingest_options(fps), overwrite=True, progress=False)
    sl = slice(None, frames)
    state, action = raw.qpos[sl], raw.action[sl]
    names = [n for n in cameras if n in views.cameras]
    T = len(state)
    with timer("fk"):
        cams = renderer.prepare_cameras({n: views.cameras[n] for n in names}, s.resolution)
        q_state = torch.as_tensor(state, dtype=torch.float32)
        q_motion = torch.as_tensor(frame_configurations(state, action, source=s.motion_source,
                                                        controller=pipe.controller), dtype=torch.float32)
        links_state = robot.link_poses(q_state)
        links_motion = robot.link_poses(q_motion)
        ref_poses = torch.stack([cams[n].pose(links_state, batch_shape=(T,)) for n in names], 1)
        fut_poses = torch.stack([cams[n].pose(links_motion, batch_shape=(T,)) for n in names], 1)
        gripper_points = pipe.gripper.points(links_motion)
    with timer("render"):
        seen = renderer.render(cameras=cams, link_poses=links_state)
        drawn = renderer.render(cameras=cams, link_poses=links_motion)
    codec = DepthCodec.preset(s.depth_codec)
    with timer("depth"):
        depth_hw = {n: resize_depth(np.asarray(depth[n][sl], dtype=np.float32), (H, W), name=n) for n in names}
        colours = {n: codec.encode_uint8(depth_hw[n]) for n in names}
    K = torch.stack([torch.as_tensor(cams[n].K, dtype=torch.float32) for n in names])
    with timer("contact"):
        contact = episode_contact(
            torch.as_tensor(np.stack([depth_hw[n] for n in names], axis=1)), K, ref_poses,
            torch.stack([seen[n].mask for n in names], 1), torch.stack([drawn[n].depth for n in names], 1),
            fut_poses, gripper_points, chunk_size=s.contact_chunk, cap=s.contact_cap,
            percentile=s.contact_percentile, dilate_px=s.robot_mask_dilate_px)
    if not full:
        return T
    streams = {}
    for v, n in enumerate(names):
        streams[f"{MOTION}.{n}"] = drawn[n].rgb.numpy()
        streams[f"{R2S}.{n}"] = contact.r2s_rgb[:, v].numpy()
        streams[f"{S2G}.{n}"] = contact.s2g_rgb[:, v].numpy()
    encoding = VideoEncoding.lossless_rgb()
    videos = tmp / "stage_videos"
    videos.mkdir(exist_ok=True)
    with timer("video_encode"):
        for key, fr in [*streams.items(), *((depth_stream_key(n), colours[n]) for n in names)]:
            encode_video(videos / f"{key}.mp4", fr, fps=int(round(fps)), encoding=encoding)
    shutil.rmtree(videos)
    with timer("augment_dataset"):
        augment_dataset(root, [EpisodeStreams(frames=streams, depth=depth_hw,
                                              caps=contact.caps.numpy().astype(np.float32))],
                        dict(views.cameras), s, source.describe())
    if shard is None:
        shutil.rmtree(root, ignore_errors=True)
    return T


def stage_times(work: Workload, size, recipe: Path, source: Path, tmp: Path) -> dict:
    from imac_data.aloha_hdf5 import episode_paths

    from lerobot.datasets.aggregate import aggregate_datasets

    from imac_data.dataset.validate import validate_dataset

    pipe = Pipeline(recipe, source)
    paths = episode_paths(source)
    episode_stages(pipe, paths[0], tmp, Timer(), frames=9, full=False)  # warm-up: allocations, caches
    timer, frames, memory = Timer(), 0, []
    timer.s["setup"] = pipe.setup_s
    # distinct paths per size: LeRobot caches video decoders by file path within a process
    shards = [tmp / f"stage_shard_{tag(size)}_{i:03d}" for i in range(len(paths))]
    t0 = time.perf_counter()
    for p, shard in zip(paths, shards):
        with PeakRSS() as rss:
            T = episode_stages(pipe, p, tmp, timer, shard=shard)
        frames += T
        memory.append({"frames": T, "working_set_mb": rss.delta_mb, "peak_rss_mb": rss.peak_mb})
    repo = "local/bench_stage"
    final = tmp / f"stage_aggregated_{tag(size)}"
    with timer("aggregate"):
        aggregate_datasets([repo] * len(shards), repo, roots=shards, aggr_root=final)
    with timer("validate"):
        validate_dataset(final).raise_if_invalid()
    wall = time.perf_counter() - t0
    for d in (*shards, final):
        shutil.rmtree(d, ignore_errors=True)
    s = dict(timer.s)
    s["write"] = max(s.pop("augment_dataset") - s["depth"] - s["video_encode"], 0.0)
    total = sum(s[k] for k in STAGES)
    V = len(VIEWS)
    ws = [m["working_set_mb"] / m["frames"] for m in memory if m["working_set_mb"] is not None]
    return {
        "size": list(size), "frames": frames, "episodes": len(paths), "wall_s": wall,
        "memory_per_episode": memory,
        "working_set_mb_per_frame": max(ws) if ws else None,
        "seconds": {k: s[k] for k in STAGES},
        "ms_per_frame": {k: 1e3 * s[k] / frames for k in STAGES},
        "fps": {k: frames / s[k] if s[k] > 0 else None for k in STAGES},
        "total_ms_per_frame": 1e3 * total / frames,
        "render_ms_per_view": 1e3 * s["render"] / (frames * V * 2),  # 2 passes: state + command
        "load_avg_end": load_avg(),
    }


def view_scaling(work: Workload, recipe: Path, source: Path, tmp: Path) -> dict:
    """Render and contact time per frame with 1, 2, 3 views (first episode, first frames)."""
    from imac_data.aloha_hdf5 import episode_paths

    pipe = Pipeline(recipe, source)
    path = episode_paths(source)[0]
    episode_stages(pipe, path, tmp, Timer(), frames=work.view_frames, full=False)  # warm-up
    rows = []
    for v in range(1, len(VIEWS) + 1):
        timer = Timer()
        T = episode_stages(pipe, path, tmp, timer, cameras=VIEWS[:v], frames=work.view_frames, full=False)
        rows.append({"views": v, "frames": T, **{f"{k}_ms_per_frame": 1e3 * timer.s[k] / T
                                                  for k in ("fk", "render", "depth", "contact")}})
    return {"size": list(work.small), "rows": rows}


# ----------------------------------------------------------------------------- 3. side by side


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

    from imac_data import aloha
    from imac_data.aloha_hdf5 import episode_paths, read_episode
    from imac_data.render import RaycastRenderer
    from imac_data.robot import RobotModel

    robot = RobotModel(aloha.robot_config())
    h, w = work.small
    q = np.concatenate([read_episode(p, load_depth=False).qpos for p in episode_paths(sources[work.small])])
    oracle = rvm.MujocoViews(TASK, h, w, robot_only=True)
    iou = {c: [] for c in VIEWS}
    try:
        calib = aloha.camera_calibration(oracle.model, w, h)
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


def run(work: Workload, tmp: Path) -> dict:
    import torch

    started = _dt.datetime.now(_dt.timezone.utc)
    t_start = time.perf_counter()
    head, dirty = commit()
    res = {"load_avg_start": load_avg()}
    sections: dict[str, dict] = {}

    def section(name):
        sections[name] = {"load_avg_start": load_avg(), "t0": time.perf_counter()}
        log(f"{name} ...")

    def done(name):
        s = sections[name]
        s["seconds"] = time.perf_counter() - s.pop("t0")
        s["load_avg_end"] = load_avg()
        log(f"{name}: {s['seconds']:.0f} s")

    errors: dict[str, str] = {}

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
    for size in work.sizes:
        recipes[size] = write_recipe(tmp / f"recipe_{tag(size)}.yaml", size, work.episodes, work.seed, work.noise)
        sources[size] = tmp / f"src_{tag(size)}"
        record_s[tag(size)] = record(work, size, sources[size])
    done("record")

    section("builds")
    builds = []
    for size, workers, episodes in work.builds():
        log(f"  build {tag(size)}, {episodes} episode(s), {workers} worker(s)")
        b = attempt(f"build {tag(size)} w{workers} e{episodes}",
                    lambda: whole_build(work, size, workers, episodes, recipes[size], sources[size], tmp))
        if b is not None:
            builds.append(b)
            log(f"    {b['frames']} frames in {b['build_s']:.1f} s = {b['fps']:.2f} fps, "
                f"peak {b['peak_mem_mb_per_worker']:.0f} MB per worker")
    done("builds")

    section("stages")
    stages = {}
    for size in work.sizes:
        st = attempt(f"stages {tag(size)}", lambda: stage_times(work, size, recipes[size], sources[size], tmp))
        if st is not None:
            stages[tag(size)] = st
            log(f"  {tag(size)}: {st['total_ms_per_frame']:.0f} ms/frame over the stages")
    views = attempt("views", lambda: view_scaling(work, recipes[work.small], sources[work.small], tmp))
    done("stages")

    section("render_vs_mujoco")
    render = attempt("render_vs_mujoco", lambda: render_comparison(work, sources), {})
    done("render_vs_mujoco")
    section("contact_speed")
    contact = attempt("contact_speed", lambda: contact_comparison(work), {})
    done("contact_speed")
    section("depth_fidelity")
    depth = attempt("depth_fidelity", lambda: depth_comparison(work), {})
    done("depth_fidelity")

    def build_of(size, workers, episodes=work.episodes):
        for b in builds:
            if tuple(b["size"]) == tuple(size) and b["workers"] == workers and b["episodes"] == episodes:
                return b
        return None

    small, large = work.sizes[0], work.sizes[-1]
    headline_build = build_of(small, max(work.workers))
    flat = {
        "fps_total_240": (headline_build or {}).get("fps"),
        "peak_mem_mb_per_worker": (headline_build or {}).get("peak_mem_mb_per_worker"),
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
    # secondary flat figures
    extra = {}
    for size in work.sizes:
        for w in work.workers:
            b = build_of(size, w)
            if b is not None:
                extra[f"fps_total_{size[0]}_w{w}"] = b["fps"]
                extra[f"peak_mem_mb_per_worker_{size[0]}_w{w}"] = b["peak_mem_mb_per_worker"]
                extra[f"bytes_per_frame_{size[0]}"] = b["bytes_per_frame"]["total"]
        st = stages.get(tag(size))
        if st is not None:
            extra[f"stages_ms_per_frame_{size[0]}"] = st["total_ms_per_frame"]
            extra[f"render_ms_per_view_pipeline_{size[0]}"] = st["render_ms_per_view"]
    for k in ("render_ms_per_view_480", "render_ratio_vs_mujoco_480", "render_ratio_vs_mujoco_all_passes"):
        extra[k] = render.get(k)
    for k in ("contact_ms_per_frame_cpu", "reference_ms_per_frame_cpu", "reference_err_max_mm_under_5cm",
              "contact_exact_ms_per_frame_cpu", "reference_default_trees_ms_per_frame_cpu"):
        extra[k] = contact.get(k)
    # contact_speed.py reports its ratio as reference / ours (a speed-up); the headline key
    # is ours / reference in time, like render_ratio_vs_mujoco (< 1 = ours faster)
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
            flat[k] = None

    # scaling
    b1 = build_of(small, 1, 1)
    bE = build_of(small, 1)
    scaling = {"views": views}
    if b1 is not None and bE is not None and bE["episodes"] > 1:
        per_ep = (bE["build_s"] - b1["build_s"]) / (bE["episodes"] - 1)
        scaling["episodes"] = {"size": list(small), "workers": 1, "build_s": {1: b1["build_s"],
                                                                             bE["episodes"]: bE["build_s"]},
                               "frames_per_episode": bE["frames"] / bE["episodes"],
                               "per_episode_s": per_ep, "fixed_s": b1["build_s"] - per_ep}
    if len(work.sizes) > 1 and tag(small) in stages and tag(large) in stages:
        a, b = stages[tag(small)], stages[tag(large)]
        scaling["resolution"] = {
            "pixels_ratio": large[0] * large[1] / (small[0] * small[1]),
            "stage_ratio": {k: (b["ms_per_frame"][k] / a["ms_per_frame"][k]) if a["ms_per_frame"][k] else None
                            for k in STAGES},
            "total_ratio": b["total_ms_per_frame"] / a["total_ms_per_frame"],
        }
    # where the time goes: stages vs the 1-worker build of the same episodes
    breakdown = {}
    for size in work.sizes:
        b = build_of(size, 1)
        st = stages.get(tag(size))
        if st is None:
            continue
        ms = dict(st["ms_per_frame"])
        if b is not None:
            ms["other"] = max(1e3 * b["build_s"] / b["frames"] - st["total_ms_per_frame"], 0.0)
        total = sum(ms.values())
        breakdown[tag(size)] = {"ms_per_frame": ms, "share": {k: v / total for k, v in ms.items()},
                                "reference": "1-worker build" if b is not None else "sum of stages"}

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
                     "frames_per_episode": (builds[0]["frames"] / builds[0]["episodes"] if builds
                                            else work.max_steps // 2),
                     "key_sizes": {"_240": tag(small), "_480": tag(large)},
                     "record_s": record_s},
        "versions": versions(),
        "torch_threads": torch.get_num_threads(),
        "extra": extra,
        "builds": builds,
        "stages": stages,
        "breakdown": breakdown,
        "scaling": scaling,
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


def _f(v, fmt=".3g", none="-"):
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return none
    return format(v, fmt)


def markdown(r: dict) -> str:
    w = r["workload"]
    small, large = w["key_sizes"]["_240"], w["key_sizes"]["_480"]
    L = [f"# imac benchmark{' (--quick smoke run: tiny sizes, figures not meaningful)' if r['quick'] else ''}", ""]
    L.append(f"`python -m benchmarks.run{' --quick' if r['quick'] else ''}` on {r['date']}, commit `{r['commit'][:12]}`"
             + (f" (+ uncommitted changes in {', '.join(r['commit_dirty_files'])})" if r["commit_dirty_files"] else "")
             + f"; {r['machine']}; {r['seconds'] / 60:.1f} min in all.")
    la = r["load_avg"]
    L.append(f"Load average (1/5/15 min) at start {la['start']}, at end {la['end']} on {os.cpu_count()} cores: the "
             "machine was shared, so timings are noisy (per-section load below).")
    L.append(f"Workload: {w['episodes']} scripted `{w['task']}` episodes (noise {w['noise']}, seeds {w['seed']}..), "
             f"{w['frames_per_episode']:.0f} frames each at 25 fps, 3 views, recorded at {small} and {large}; "
             "one frame = 3 views x (base RGB + motion + depth + contact r2s + contact s2g).")

    sizes = list(r.get("stages") or {})
    cr = r.get("contact_vs_reference") or {}

    def _headline():
        nonlocal L
        L += ["", "## Headline figures", "", "| key | value | what |", "|---|---|---|"]
        what = {
            "fps_total_240": f"whole build (`build()`), frames/s, {small}, {max(w['workers'])} workers",
            "peak_mem_mb_per_worker": f"peak RSS of the largest build worker, {small}, {max(w['workers'])} workers",
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
        L.append("\nBoth ratios are ours / theirs in time (< 1 = ours faster). `benchmarks/contact_speed.py` itself "
                 "reports the inverse (reference / ours) under the same name; here that is "
                 "`extra.contact_speedup_vs_reference` = "
                 f"{_f(r['extra'].get('contact_speedup_vs_reference'), '.1f')}x.")


    def _whole_build():
        nonlocal L
        L += ["", "## Whole build (`imac_data.build.build`, end to end)", "",
              "| size | workers | episodes | frames | build s | frames/s | CLI wall s | peak RSS per worker MB | "
              "coordinator MB | output KB/frame | load at end |", "|---|---|---|---|---|---|---|---|---|---|---|"]
        for b in r["builds"]:
            L.append(f"| {tag(b['size'])} | {b['workers']} | {b['episodes']} | {b['frames']} | {b['build_s']:.1f} | "
                     f"{b['fps']:.2f} | {b['cli_wall_s']:.1f} | {b['peak_mem_mb_per_worker']:.0f} | "
                     f"{b['peak_mem_mb_coordinator']:.0f} | {b['bytes_per_frame']['total'] / 1024:.1f} | "
                     f"{b['load_avg_end'][0]} |")
        L.append("\n(build s: `build()` alone; CLI wall: the subprocess incl. interpreter start and imports. "
                 "With 1 worker the episodes run in the coordinator, so its RSS is the worker's.)")


    def _stages():
        nonlocal L
        L += ["", "## Time per stage (ms per frame; one process, the build's stage functions on the same episodes)", ""]
        hdr = "| stage | " + " | ".join(f"{s} ms/frame | {s} fps | {s} share" for s in sizes) + " |"
        L += [hdr, "|---|" + "---|" * (3 * len(sizes))]
        for k in (*STAGES, "other"):
            cells = []
            for s in sizes:
                bd = r["breakdown"][s]
                ms = bd["ms_per_frame"].get(k)
                share = _f(100 * bd["share"].get(k, 0), ".0f") + " %" if ms is not None else "-"
                cells += [_f(ms, ".1f"), _f(1e3 / ms if ms else None, ".1f"), share]
            L.append(f"| {STAGE_LABELS[k]} | " + " | ".join(cells) + " |")
        tot = []
        for s in sizes:
            bd = r["breakdown"][s]
            t = sum(bd["ms_per_frame"].values())
            tot += [f"{t:.0f}", f"{1e3 / t:.2f}", "100 %"]
        L.append("| **total (= 1-worker build per frame)** | " + " | ".join(tot) + " |")
        L.append("\nPer frame of this workload: fixed costs (setup, aggregate, validate, other) are spread over its "
                 f"{w['episodes']} x {w['frames_per_episode']:.0f} frames, so they weigh less on longer episodes.")
        L.append("\nRender per view and pass (state + command, pipeline batches): "
                 + ", ".join(f"{s} {r['stages'][s]['render_ms_per_view']:.1f} ms" for s in sizes) + ".")


    def _output_bytes():
        nonlocal L
        L += ["", "## Output bytes per frame (3 views)", "",
              "| size | " + " | ".join(STREAM_GROUPS) + " | tabular (parquet + meta) | total |",
              "|---|" + "---|" * (len(STREAM_GROUPS) + 2)]
        seen = set()
        for b in r["builds"]:
            if tag(b["size"]) in seen or b["episodes"] != w["episodes"]:
                continue
            seen.add(tag(b["size"]))
            bp = b["bytes_per_frame"]
            L.append(f"| {tag(b['size'])} | " + " | ".join(f"{bp[g] / 1024:.1f} KB" for g in STREAM_GROUPS)
                     + f" | {bp['tabular'] / 1024:.1f} KB | {bp['total'] / 1024:.1f} KB |")


    def _scaling():
        nonlocal L
        sc = r["scaling"]
        L += ["", "## How cost grows", ""]
        if "episodes" in sc:
            e = sc["episodes"]
            L.append(f"* **Episodes** ({tag(e['size'])}, 1 worker): build = {e['fixed_s']:.1f} s fixed + "
                     f"{e['per_episode_s']:.1f} s per episode of {e['frames_per_episode']:.0f} frames "
                     f"({1e3 * e['per_episode_s'] / e['frames_per_episode']:.0f} ms/frame); builds of "
                     + ", ".join(f"{n} episode(s) {s:.1f} s" for n, s in e["build_s"].items()) + ".")
        if "resolution" in sc:
            res = sc["resolution"]
            L.append(f"* **Resolution** {small} -> {large} ({res['pixels_ratio']:.0f}x pixels): stages "
                     f"{res['total_ratio']:.1f}x per frame; per stage "
                     + ", ".join(f"{k} {v:.1f}x" for k, v in res["stage_ratio"].items() if v is not None) + ".")
        mem = [f"{s} {r['stages'][s]['working_set_mb_per_frame']:.1f} MB" for s in sizes
               if r["stages"][s].get("working_set_mb_per_frame") is not None]
        if mem:
            L.append("* **Memory** grows with episode *length*, not with the number of episodes (a worker holds one "
                     "episode's frames, renders and distance maps at a time): working set per frame of the episode "
                     + ", ".join(mem) + "; peak RSS per worker in the builds above = that x frames per episode + the "
                     "process's base (imports, robot, renderer).")
        ws = {b["workers"]: b for b in r["builds"] if tag(b["size"]) == small and b["episodes"] == w["episodes"]}
        if len(ws) > 1:
            lo, hi = min(ws), max(ws)
            L.append(f"* **Workers** ({small}): {lo} -> {hi} workers = {ws[hi]['fps'] / ws[lo]['fps']:.2f}x frames/s "
                     f"({ws[lo]['fps']:.2f} -> {ws[hi]['fps']:.2f}).")
        v = sc["views"]
        L += ["", f"Views ({tag(v['size'])}, first {v['rows'][0]['frames']} frames of episode 0, ms per frame):", "",
              "| views | FK | render | depth | contact |", "|---|---|---|---|---|"]
        for row in v["rows"]:
            L.append(f"| {row['views']} | {row['fk_ms_per_frame']:.1f} | {row['render_ms_per_frame']:.1f} | "
                     f"{row['depth_ms_per_frame']:.1f} | {row['contact_ms_per_frame']:.1f} |")


    def _where():
        nonlocal L
        L += ["", "## Where the time goes", ""]
        for s in sizes:
            bd = r["breakdown"][s]
            top = sorted(bd["share"].items(), key=lambda kv: -kv[1])[:4]
            L.append(f"* {s}: " + ", ".join(f"{k} {100 * v:.0f} %" for k, v in top)
                     + f" of {sum(bd['ms_per_frame'].values()):.0f} ms/frame ({bd['reference']}).")


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

    for part in (_headline, _whole_build, _stages, _output_bytes, _scaling, _where, _side_by_side, _errors, _sections):
        n = len(L)
        try:
            part()
        except Exception as e:  # noqa: BLE001  (a section of a partial result)
            del L[n:]
            L += ["", f"({part.__name__.strip('_')}: not available, {type(e).__name__}: {e})"]
    return "\n".join(L) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.run", description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="CI smoke run: tiny sizes, few frames (figures not meaningful)")
    p.add_argument("--episodes", type=int, help="episodes in the workload (default 2)")
    p.add_argument("--max-steps", type=int, help="50 Hz steps per episode (frames = steps / 2; default 96)")
    p.add_argument("--render-frames", type=int, help="render_vs_mujoco timing frames per size (default 32)")
    p.add_argument("--contact-reference-frames", type=int, help="frames the slow contact reference runs on (default 8)")
    p.add_argument("--no-episode-scaling", action="store_true", help="skip the extra 1-episode build")
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
                       ("contact_reference_frames", "contact_reference_frames")):
        if getattr(a, flag) is not None:
            setattr(work, attr, getattr(a, flag))
    if a.no_episode_scaling:
        work.episode_scaling = False
    if work.episodes < 1 or work.max_steps < 2:
        p.error("--episodes must be >= 1 and --max-steps >= 2")

    from imac_data.cli import quiet_libraries

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
