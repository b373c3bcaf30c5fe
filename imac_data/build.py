"""The main job: ``python -m imac_data.build --repo local/<name>``.

Flow (one way): recipe -> source episodes (recorded in simulation when the recipe
says so) -> checks -> base LeRobot dataset (:mod:`imac_data.ingest`) -> validation.
The augmentation stages (motion, depth, contact streams) plug in after ingest.

The output lands where LeRobot looks for ``repo_id`` (``$HF_LEROBOT_HOME/<repo>``)
unless ``--root`` says otherwise; it is assembled in a staging directory and
moved into place only when complete, under an OS lock that keeps a second build of
the same output out (:mod:`imac_data.lock`). The source data is only read. Failures exit
with the codes of :mod:`imac_data.cli` (2 bad input, 3 the environment); the README's
"Safety" section lists what is guaranteed and the tests that check it.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

from imac_data.cli import (cache_home, default_root, interrupted, quiet_libraries, run_command,
                           silence_progress_bars)
from imac_data.errors import InputError
from imac_data.joint_ranges import joint_range_warning
from imac_data.recipes import Recipe, find_recipe, load_recipe, missing_inputs
from imac_data.safety import check_output, make_sibling_dir, refuse_overlap, remove_sibling, swap_into_place


@dataclass(frozen=True)
class BuildRequest:
    repo_id: str
    recipe: Recipe
    root: Path
    source_path: Path | None = None  # overrides recipe.source.path
    episodes: int | None = None  # overrides recipe.source.episodes
    overwrite: bool = False
    progress: bool = True
    timings: Path | None = None  # also write the build's stage timings here (JSON)
    wait: bool = False  # wait for another build of the same root instead of refusing (imac_data.lock)

    def __post_init__(self):
        # absolute, as its siblings are (safety.output_sibling): the swap renames the root itself
        object.__setattr__(self, "root", Path(os.path.abspath(self.root)))


# --------------------------------------------------------------------------- stages


def source_episodes(req: BuildRequest) -> tuple[list[Path], Path]:
    """The episode files to ingest and the calibration file that goes with them."""
    from imac_data.aloha_hdf5 import episode_paths

    recipe, src = req.recipe, req.recipe.source
    n = req.episodes if req.episodes is not None else src.episodes
    path = req.source_path or recipe.resolve_path(src.path)
    if src.type == "aloha_sim" and (path is None or not path.exists()):
        path = record_sim_episodes(recipe, n, path, req.progress)
    if path is None or not path.exists():
        raise InputError(f"source path does not exist: {path}")
    paths = episode_paths(path)
    if n is not None:
        if n > len(paths):
            raise InputError(f"{path}: asked for {n} episodes, the directory has {len(paths)}")
        paths = paths[:n]
    calibration = recipe.resolve_path(recipe.cameras.calibration) or path / "calibration.json"
    if not calibration.is_file():
        raise InputError(
            f"calibration file not found: {calibration} (set cameras.calibration in {recipe.file or 'the recipe'})"
        )
    return paths, calibration


def record_sim_episodes(recipe: Recipe, n: int | None, path: Path | None, progress: bool) -> Path:
    """Record the recipe's simulated episodes (once; later builds reuse them)."""
    from imac_data.simulate import SimConfig, record_dataset

    sim = recipe.source.sim
    config = SimConfig(task=sim.task, num_episodes=n or 2, width=sim.width, height=sim.height, seed=sim.seed,
                       noise=sim.noise, frame_stride=sim.frame_stride, with_segmentation=sim.segmentation)
    if path is None:
        key = hashlib.sha256(json.dumps(asdict(config), sort_keys=True).encode()).hexdigest()[:12]
        path = cache_home() / "sim" / f"{recipe.name}-{key}"
    if (path / "calibration.json").is_file() and len(list(path.glob("episode_*.hdf5"))) >= config.num_episodes:
        return path
    print(f"[build] recording {config.num_episodes} simulated {sim.task} episodes into {path}", file=sys.stderr)
    record_dataset(config, path, progress=progress, overwrite=True)
    return path


# --------------------------------------------------------------------------- per-episode shards


@dataclass(frozen=True)
class ShardJob:
    """The unit of work: one source episode -> one complete one-episode dataset (base
    features + control streams) at ``shard_dir``. Local processes and Ray tasks run the
    same :func:`build_shard`; a shard directory appears atomically, so a killed build
    resumes with the shards that are missing. The rig travels as its ``info.json`` block
    plus the packaged robot description in the staging directory: every worker renders
    exactly the robot the dataset will carry. ``threads``: the worker's share of the cores.
    Its stage timings go to ``timings_file`` (staging, never the dataset)."""

    index: int
    episode: Path
    shard_dir: Path
    repo_id: str
    settings: object  # AugmentSettings
    rig_block: dict
    description_dir: Path
    options: object  # IngestOptions
    timings_file: Path
    threads: int = 1
    depth: object = None  # the recipe's DepthSection (None: recorded depth)
    recipe_file: str = ""  # for the depth section's relative model paths


_PROCESS_CACHE: dict = {}
_DEPTH_CACHE: dict = {}


def worker_depth_source(section, recipe_file: str, num_cameras: int, timer=None):
    """The recipe's depth source, built once per worker process (a DA3 model loads once)."""
    import contextlib

    from imac_data.depth_choice import make_depth_source

    if section is None:
        return None
    key = (repr(section), recipe_file, num_cameras)
    if key not in _DEPTH_CACHE:
        with timer("setup") if timer is not None else contextlib.nullcontext():
            _DEPTH_CACHE.clear()
            _DEPTH_CACHE[key] = make_depth_source(section, recipe_file, num_cameras)
    return _DEPTH_CACHE[key]


def worker_rig(block: dict, description_dir: Path, timer=None):
    """The rig of a job, built once per worker process (the Open3D scene cannot be pickled,
    so each process builds its own renderer); the first build is timed as ``setup``."""
    from imac_data.rig import Rig

    key = (str(description_dir), json.dumps(block, sort_keys=True))
    if key not in _PROCESS_CACHE:
        import contextlib

        with timer("setup") if timer is not None else contextlib.nullcontext():
            rig = Rig.from_block(block, description_dir)
            rig.renderer, rig.gripper  # noqa: B018 - built here, counted as setup
        _PROCESS_CACHE.clear()
        _PROCESS_CACHE[key] = rig
    return _PROCESS_CACHE[key]


def build_shard(job: ShardJob) -> Path:
    """Build one episode's shard dataset (idempotent: a finished shard is kept)."""
    import shutil

    from imac_data.pipeline import StageTimer, write_episode_dataset, write_timings
    from imac_data.workers import pin_threads, raise_if_interrupted

    if (job.shard_dir / "meta" / "info.json").is_file():
        return job.shard_dir
    raise_if_interrupted()
    pin_threads(job.threads)
    timer = StageTimer()
    wall, cpu = time.perf_counter(), time.process_time()
    rig = worker_rig(job.rig_block, job.description_dir, timer)
    depth_source = worker_depth_source(job.depth, job.recipe_file, len(rig.names), timer)
    tmp = job.shard_dir.with_name(f".{job.shard_dir.name}.tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        write_episode_dataset(job.episode, tmp, job.repo_id, rig, job.settings, job.options, timer=timer,
                              threads=job.threads, with_description=False, depth_source=depth_source)
        tmp.rename(job.shard_dir)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    from imac_data.workers import peak_rss_mb

    write_timings(job.timings_file, timer, episode=str(job.episode), threads=job.threads, pid=os.getpid(),
                  shard_wall_s=time.perf_counter() - wall, shard_cpu_s=time.process_time() - cpu,
                  peak_rss_mb=peak_rss_mb())
    return job.shard_dir


def _init_worker(threads: int, parent_pid: int) -> None:
    from imac_data.workers import exit_with_parent, pin_threads, quiet_worker_interrupts

    exit_with_parent(parent_pid)  # first: the imports below take seconds
    quiet_worker_interrupts()
    pin_threads(threads)
    quiet_libraries()


def run_jobs(jobs: list[ShardJob], *, executor: str, workers: int, ray_address: str | None,
             progress: bool) -> None:
    """Run the shard jobs that are not done yet: in this process (1 worker), a local
    process pool, or Ray tasks; each worker's thread pools pinned to ``job.threads``."""
    from tqdm.auto import tqdm

    from imac_data.workers import thread_env

    todo = [j for j in jobs if not (j.shard_dir / "meta" / "info.json").is_file()]
    bar = tqdm(total=len(jobs), initial=len(jobs) - len(todo), desc="build episodes", unit="ep",
               disable=not progress)
    try:
        if not todo:
            return
        threads = todo[0].threads
        if executor == "ray":
            import ray

            if not ray.is_initialized():
                ray.init(address=ray_address, num_cpus=None if ray_address else workers,
                         include_dashboard=False, log_to_driver=False, logging_level="ERROR",
                         runtime_env={"env_vars": thread_env(threads)})
            task = ray.remote(num_cpus=1)(_ray_shard)
            pending = [task.remote(j) for j in todo]
            while pending:
                done, pending = ray.wait(pending, num_returns=1)
                ray.get(done)
                bar.update(len(done))
        elif workers <= 1 or len(todo) == 1:
            for job in todo:
                build_shard(job)
                bar.update(1)
        else:
            _run_local_pool(todo, workers, threads, bar)
    finally:
        bar.close()


def _run_local_pool(todo: list[ShardJob], workers: int, threads: int, bar) -> None:
    """``workers`` workers pull episodes from one queue: this process is one of them (its
    libraries are loaded already: a spawned worker first spends about 7 CPU-seconds on
    imports), the others are spawned pool processes. The episodes' bytes do not depend on
    who builds them."""
    import multiprocessing as mp
    import queue
    import threading
    from concurrent.futures import ProcessPoolExecutor

    from imac_data.workers import block_interrupts_in_this_thread, raise_if_interrupted, run_as_job, thread_env

    jobs: queue.Queue = queue.Queue()
    for job in todo:
        jobs.put(job)
    errors: list[BaseException] = []
    lock = threading.Lock()

    def worker(run, *, remote: bool = True) -> None:
        if remote:  # Ctrl-C goes to this process's main thread; the workers these threads start hold it
            block_interrupts_in_this_thread()
        while not errors:
            try:
                job = jobs.get_nowait()
            except queue.Empty:
                return
            try:
                run(job)
            except BaseException as e:  # noqa: BLE001 - re-raised in the caller's thread
                errors.append(e)
                return
            with lock:
                bar.update(1)

    saved = {k: os.environ.get(k) for k in thread_env(threads)}
    os.environ.update(thread_env(threads))  # pool workers size their pools at import
    try:
        with ProcessPoolExecutor(max_workers=workers - 1, mp_context=mp.get_context("spawn"), initializer=_init_worker,
                                 initargs=(threads, os.getpid())) as pool:
            remote = [threading.Thread(target=worker, args=(lambda j: pool.submit(run_as_job, build_shard, j).result(),))
                      for _ in range(workers - 1)]
            for t in remote:
                t.start()
            worker(build_shard, remote=False)  # this process builds episodes too
            for t in remote:
                t.join()
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    raise_if_interrupted()  # a Ctrl-C first: the workers it ended show up as a broken pool
    if errors:
        raise next((e for e in errors if interrupted(e)), errors[0])


def _ray_shard(job: ShardJob) -> str:
    quiet_libraries()
    return str(build_shard(job))


def build_key(recipe: Recipe, paths: list[Path], calibration_path: Path, repo_id: str, rig_block: dict) -> str:
    """What a resumable staging directory was built for: the recipe, the source files
    (path, size, mtime), the calibration, the rig (``rig_block``: its ``info["imac"]`` part,
    which holds the sha256 of the URDF and of every mesh, so an edited robot description
    starts over too) and our code. A different key starts over."""
    from imac_data import __version__

    h = hashlib.sha256()
    h.update(json.dumps([repo_id, __version__, repr(recipe), rig_block], default=str, sort_keys=True).encode())
    for src in sorted(Path(__file__).parent.rglob("*.py")):  # the code that made the shards
        h.update(src.read_bytes())
    for p in [*paths, calibration_path]:
        st = p.stat()
        h.update(f"{p.resolve()}|{st.st_size}|{st.st_mtime_ns}".encode())
    return h.hexdigest()


def build(req: BuildRequest, *, executor: str = "local", workers: int | None = None,
          ray_address: str | None = None):
    """Run the whole build; returns the loaded LeRobotDataset at ``req.root``. Everything
    is checked first (read-only), then the output's lock is taken for the writing part."""
    import resource

    t_start, usage_start = time.perf_counter(), _cpu_seconds(resource)

    from imac_data.ingest import IngestOptions, check_episodes
    from imac_data.lock import output_lock
    from imac_data.rig import Rig
    from imac_data.workers import limit_malloc_arenas

    limit_malloc_arenas()  # before the rig's threads allocate: this process may be the only worker

    recipe = req.recipe
    if executor not in ("local", "ray"):
        raise InputError(f"--executor must be 'local' or 'ray', got {executor!r}")
    problems = missing_inputs(recipe, req.source_path)
    if problems:
        raise InputError(f"recipe {recipe.file} needs inputs that are not there:\n  - " + "\n  - ".join(problems))
    refuse_overlap(req.root, _input_paths(req))  # before anything is recorded or written
    check_output(req.root, overwrite=req.overwrite)
    robot = Rig.robot_from_recipe(recipe)  # a bad URDF or joint map fails before any recording
    if recipe.source.type == "lerobot":
        from imac_data.lerobot_build import build_from_lerobot

        with output_lock(req.root, wait=req.wait):  # it stages next to the output too
            return build_from_lerobot(req, robot)
    paths, calibration_path = source_episodes(req)
    refuse_overlap(req.root, {"source episodes": paths[0].parent, "calibration": calibration_path})
    rig = Rig.from_recipe(recipe, calibration_path, robot=robot)
    probe = check_episodes(paths, rig.cameras, robot)
    warning = joint_range_warning(robot, *probe["qpos_range"], source=f"the episodes in {paths[0].parent}",
                                  recipe=recipe.file or "the recipe")
    if warning:
        print(warning, file=sys.stderr)
    from imac_data.depth_choice import check_depth_inputs

    check_depth_inputs(recipe.depth, recipe.file, len(rig.names))
    _check_stream_resolution(recipe, rig.cameras)
    _warn_if_short_of_space(req, probe, robot)
    fps = recipe.fps if recipe.fps is not None else probe["fps"]  # check_episodes: the same in every episode
    if fps is None:
        raise InputError(f"{recipe.file}: fps: the episodes do not record their rate; set fps in the recipe")
    if not float(fps).is_integer():  # LeRobot stores an integer fps and stamps frame i at i / fps (the recipe's is)
        raise InputError(f"{paths[0]}: attribute 'fps' is {fps}: a LeRobot dataset has a whole number of frames per "
                         "second; set fps in the recipe to the rate its timestamps should use")
    defaults = recipe.source.episode_defaults
    options = IngestOptions(
        fps=fps, task=recipe.task, source=defaults.source, policy_name=defaults.policy_name,
        checkpoint=defaults.checkpoint, robot_type=robot.name, state_names=rig.state_names,
    )

    # Staging: shards/ (one dataset per episode, kept across a killed run when the
    # build key matches), then the aggregated dataset, renamed into place at the end;
    # one build at a time per output (imac_data.lock).
    with output_lock(req.root, wait=req.wait):
        check_output(req.root, overwrite=req.overwrite)  # again: a build we waited for may have made it
        return _build_staged(req, paths, calibration_path, rig, robot, options, executor=executor,
                             workers=workers, ray_address=ray_address, t_start=t_start, usage_start=usage_start)


def _build_staged(req: BuildRequest, paths, calibration_path, rig, robot, options, *, executor, workers,
                  ray_address, t_start, usage_start):
    """The build's writing part, under the output's lock: shards, merge, validation, swap."""
    import resource
    import shutil

    from imac_data.dataset.merge import merge_datasets
    from imac_data.dataset.validate import validate_dataset
    from imac_data.dataset_card import write_card
    from imac_data.ingest import staging_dir
    from imac_data.pipeline import StageTimer
    from imac_data.robot_files import write_description
    from imac_data.workers import default_workers, threads_per_worker

    recipe = req.recipe
    staging = staging_dir(req.root)
    block = rig.to_info()
    key = build_key(recipe, paths, calibration_path, req.repo_id, block)
    key_file = staging / "BUILD_KEY"
    if staging.exists() and (not key_file.is_file() or key_file.read_text() != key):
        remove_sibling(staging)
    if not staging.exists():
        make_sibling_dir(staging)
    (staging / "shards").mkdir(exist_ok=True)
    key_file.write_text(key)
    description = staging / "robot"
    write_description(robot, description)
    workers = workers or default_workers(len(paths))
    threads = threads_per_worker(min(workers, len(paths)))
    jobs = [ShardJob(i, p, staging / "shards" / f"episode_{i:06d}", req.repo_id, recipe.augment, block, description,
                     options, staging / "timings" / f"episode_{i:06d}.json", threads, recipe.depth, recipe.file)
            for i, p in enumerate(paths)]
    t_jobs = time.perf_counter()
    run_jobs(jobs, executor=executor, workers=workers, ray_address=ray_address, progress=req.progress)
    t_jobs = time.perf_counter() - t_jobs

    timer = StageTimer()  # the build's own stages, in this process
    final = staging / "dataset"
    shutil.rmtree(final, ignore_errors=True)
    try:  # a failed merge or validation leaves the shards, never a half-merged dataset
        with timer("merge"):
            merge_datasets([j.shard_dir for j in jobs], final, req.repo_id, description_dir=description,
                           imac_extra={"build": {"recipe": recipe.name, "episodes": len(jobs),
                                                 "command": f"python -m imac_data.build --repo {req.repo_id}"}})
            write_card(final, req.repo_id, recipe)
        with timer("validate"):  # first and last frame of every episode, every stream
            validate_dataset(final, sample=2).raise_if_invalid()
    except BaseException:
        shutil.rmtree(final, ignore_errors=True)
        raise
    report = _timings_report(jobs, timer, workers=workers, threads=threads, executor=executor,
                             episodes_wall_s=t_jobs, wall_s=time.perf_counter() - t_start,
                             cpu_s=_cpu_seconds(resource) - usage_start)
    (staging / "timings.json").write_text(json.dumps(report, indent=1))
    if req.timings is not None:
        req.timings.parent.mkdir(parents=True, exist_ok=True)
        req.timings.write_text(json.dumps(report, indent=1))
    if req.progress:
        print(_timings_table(report), file=sys.stderr)

    swap_into_place(final, req.root)
    shutil.rmtree(staging, ignore_errors=True)
    # Imported here, not before the jobs: LeRobot's import takes 1.4 s, and the pool
    # workers are spawned only when the jobs start (the build process imports it in its
    # first episode anyway, while the spawned workers import theirs).
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    return LeRobotDataset(req.repo_id, root=req.root)


def _warn_if_short_of_space(req: BuildRequest, probe: dict, robot) -> None:
    from imac_data.diskspace import estimate_build_bytes, warn_if_short_of_space
    from imac_data.robot_files import description_bytes

    need = estimate_build_bytes(probe["total_frames"], probe["image_hw"], req.recipe.augment.resolution,
                                description_bytes(robot))
    warn_if_short_of_space(req.root, need)


def _cpu_seconds(resource) -> float:
    """CPU seconds of this process and its finished child processes (pool workers)."""
    own, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


def _timings_report(jobs, timer, **summary) -> dict:
    """Stage timings of a build: per episode (the workers' side files) and their sum, plus
    the build's own stages; written to ``timings.json`` in staging (never the dataset)."""
    from imac_data.pipeline import StageTimer

    total = StageTimer()
    episodes = []
    for job in jobs:
        if job.timings_file.is_file():  # a resumed build has no timings for shards it did not redo
            d = json.loads(job.timings_file.read_text())
            episodes.append(d)
            total.add(d)
    total.add(timer)
    return {**summary, "frames": total.frames, "episodes_timed": len(episodes),
            "stages": total.to_dict(), "episodes": episodes}


def _timings_table(report: dict) -> str:
    from imac_data.pipeline import StageTimer

    t = StageTimer()
    t.add(report["stages"])
    frames = max(report["frames"], 1)
    head = (f"[build] {report['frames']} frames, {report['workers']} worker(s) x {report['threads']} thread(s) "
            f"({report['executor']}): {report['wall_s']:.1f} s wall ({frames / report['wall_s']:.2f} frames/s), "
            f"{report['cpu_s']:.1f} s CPU here and in pool workers ({report['cpu_s'] / frames * 1e3:.0f} ms/frame)")
    return head + "\n" + t.table("[build] stage")


def _input_paths(req: BuildRequest) -> dict[str, Path | None]:
    """The user's files a build reads (never written or deleted: :mod:`imac_data.safety`)."""
    recipe = req.recipe
    return {
        "source dataset" if recipe.source.type == "lerobot" else "source episodes":
            req.source_path or recipe.resolve_path(recipe.source.path),
        "calibration": recipe.resolve_path(recipe.cameras.calibration),
        "recipe": Path(recipe.file) if recipe.file else None,
        "robot URDF": recipe.resolve_path(recipe.robot.urdf),
        "episode metadata": recipe.resolve_path(recipe.source.metadata),
    }


def _check_stream_resolution(recipe: Recipe, calibration) -> None:
    """The added streams keep each camera's aspect ratio (they are rescaled, not cropped)."""
    from imac_data.cameras import same_aspect

    h, w = recipe.augment.resolution
    for cam in calibration.values():
        if not same_aspect((h, w), (cam.height, cam.width)):
            raise InputError(
                f"{recipe.file}: augment.height/width {h}x{w} has another aspect ratio than camera {cam.name!r} "
                f"({cam.height}x{cam.width}); pick a size of the same aspect ratio"
            )


# --------------------------------------------------------------------------- CLI


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m imac_data.build",
        description="Build a LeRobot dataset with iMaC control streams from a recipe.",
    )
    p.add_argument("--repo", required=True, help="dataset repo id, e.g. local/aloha_sim_transfer_cube")
    p.add_argument("--recipe", type=Path, help="recipe YAML (default: recipes/<name of --repo>.yaml)")
    p.add_argument("--root", type=Path, help="output directory (default: $HF_LEROBOT_HOME/<repo>)")
    p.add_argument("--source", type=Path, help="directory of raw episodes (overrides the recipe's source.path)")
    p.add_argument("--episodes", type=int, help="use the first N episodes (overrides the recipe)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output dataset")
    p.add_argument("--workers", type=int,
                   help="parallel episode workers, each pinned to its share of the cores (default: one per core, "
                        "at most one per episode)")
    p.add_argument("--executor", choices=("local", "ray"), default="local",
                   help="local process pool (default) or Ray tasks")
    p.add_argument("--ray-address", help="Ray cluster address (default: start a local Ray)")
    p.add_argument("--push-to-hub", action="store_true",
                   help="upload the result with LeRobot's push_to_hub (needs `huggingface-cli login`)")
    p.add_argument("--private", action="store_true", help="with --push-to-hub: a private dataset repo")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.add_argument("--timings", type=Path, help="write the build's stage timings (JSON) here as well")
    p.add_argument("--wait", action="store_true",
                   help="if another build is writing the same output, wait for it (default: refuse, exit 3)")
    args = p.parse_args(argv)

    quiet_libraries()
    if args.no_progress:
        silence_progress_bars()
    return run_command(lambda: _run(args))


def _run(args: argparse.Namespace) -> int:
    t0 = time.perf_counter()
    if "/" not in args.repo:
        raise InputError(f"--repo must look like <user>/<name>, got {args.repo!r}")
    recipe_path = args.recipe or find_recipe(args.repo.split("/", 1)[1])
    recipe = load_recipe(recipe_path)
    if args.episodes is not None and args.episodes <= 0:
        raise InputError(f"--episodes must be positive, got {args.episodes}")
    if args.source is not None and not args.source.exists():
        raise InputError(f"--source: path does not exist: {args.source}")
    req = BuildRequest(
        repo_id=args.repo, recipe=recipe, root=args.root or default_root(args.repo),
        source_path=args.source, episodes=args.episodes, overwrite=args.overwrite,
        progress=not args.no_progress, timings=args.timings, wait=args.wait,
    )
    if args.workers is not None and args.workers <= 0:
        raise InputError(f"--workers must be positive, got {args.workers}")
    dataset = build(req, executor=args.executor, workers=args.workers, ray_address=args.ray_address)
    dt = time.perf_counter() - t0
    if args.push_to_hub:
        from imac_data.dataset_card import push_to_hub

        push_to_hub(req.root, args.repo, recipe, private=args.private)
        print(f"pushed {args.repo} to the hub")
    size = sum(f.stat().st_size for f in req.root.rglob("*") if f.is_file())
    frames = dataset.meta.total_frames
    print(
        f"built {args.repo}: {dataset.meta.total_episodes} episodes, {frames} frames in {dt:.1f} s "
        f"({frames / dt:.1f} frames/s), {size / 1e6:.1f} MB at {req.root}"
    )
    return 0


if __name__ == "__main__":
    from imac_data.cli import exit_process

    exit_process(main())
