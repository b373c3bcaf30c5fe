"""Build workers: one episode -> one shard, run in this process, a local process pool or Ray
tasks, each worker's thread pools pinned to its share of the cores.

None of the pools changes a result (x264, whose output depends on its thread count, runs
with a fixed one), so a build's bytes do not depend on ``--workers``, the executor or the
machine. A pool worker dies with the build that started it. ``docs/building.md`` has the
measurements behind the defaults.
"""

from __future__ import annotations

import contextlib
import json
import multiprocessing as mp
import os
import queue
import resource
import shutil
import signal
import threading
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import cv2
import torch
from tqdm.auto import tqdm

from imac_data.augment.timing import StageTimer
from imac_data.build.streams import write_episode_dataset, write_timings
from imac_data.console import (
    MALLOC_ARENAS,
    block_interrupts_in_this_thread,
    cpu_cores,
    interrupted,
    limit_malloc_arenas,
    quiet_libraries,
    quiet_worker_interrupts,
    raise_if_interrupted,
    run_as_job,
)
from imac_data.core.rig import Rig
from imac_data.layout import INFO
from imac_data.sources.depth import make_depth_source

__all__ = ["ShardJob", "build_shard", "run_jobs", "run_local", "cpu_cores", "default_workers", "threads_per_worker", "pin_threads",
           "thread_env", "peak_rss_mb", "exit_with_parent", "limit_malloc_arenas"]

_THREAD_VARS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMEXPR_NUM_THREADS")


def default_workers(episodes: int, cores: int | None = None) -> int:
    """``--workers`` when none is given: one worker per core, at most one per episode. Whole
    episodes side by side scale better than threads inside one worker, which pays for a
    spawned worker's imports (``docs/building.md``, "Workers, memory and speed")."""
    cores = cores or cpu_cores()
    return max(1, min(int(episodes), cores))


def threads_per_worker(workers: int, cores: int | None = None) -> int:
    return max(1, (cores or cpu_cores()) // max(1, int(workers)))


def thread_env(threads: int) -> dict[str, str]:
    """Environment for a new worker process: libraries that size their pools when loaded,
    and glibc's malloc arenas."""
    return {**{var: str(threads) for var in _THREAD_VARS}, "MALLOC_ARENA_MAX": str(MALLOC_ARENAS)}


def pin_threads(threads: int) -> None:
    """Cap this process's thread pools at ``threads`` (torch, OpenCV; the renderer, contact
    queries and encoders take theirs from the rig / pipeline settings)."""
    threads = max(1, int(threads))
    for var, value in thread_env(threads).items():
        os.environ[var] = value  # for anything loaded later (and child processes)
    torch.set_num_threads(threads)
    cv2.setNumThreads(threads)
    limit_malloc_arenas()


def peak_rss_mb() -> float:
    """This process's peak resident memory in MB: ``VmHWM`` (Linux; starts afresh at
    ``exec``). ``getrusage``'s ``ru_maxrss`` is no substitute for a worker started from a
    big parent: Linux carries the parent's peak over ``fork`` + ``exec``."""
    try:
        for line in open("/proc/self/status"):
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def exit_with_parent(parent_pid: int, interval_s: float = 0.2) -> None:
    """Kill this process as soon as its parent ``parent_pid`` is gone (the orphan is
    re-parented, so ``getppid`` changes), from a daemon thread that polls every ``interval_s``.

    Why not ``prctl(PR_SET_PDEATHSIG)``: Linux sends that signal when the *thread* that
    started the process ends, and a process pool starts its workers from whichever thread
    submits first (the build's feeder threads, which end before the pool does), so it
    would kill live workers. The poll costs nothing measurable."""
    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(interval_s)
        os.kill(os.getpid(), signal.SIGKILL)

    threading.Thread(target=watch, name="exit-with-parent", daemon=True).start()


# ----------------------------------------------------------------------------- shard jobs


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
    device: str = "cpu"  # where the worker renders and paints contact (Rig.device)


_PROCESS_CACHE: dict = {}
_DEPTH_CACHE: dict = {}


def worker_depth_source(section, recipe_file: str, num_cameras: int, timer=None):
    """The recipe's depth source, built once per worker process (a DA3 model loads once)."""
    if section is None:
        return None
    key = (repr(section), recipe_file, num_cameras)
    if key not in _DEPTH_CACHE:
        with timer("setup") if timer is not None else contextlib.nullcontext():
            _DEPTH_CACHE.clear()
            _DEPTH_CACHE[key] = make_depth_source(section, recipe_file, num_cameras)
    return _DEPTH_CACHE[key]


def worker_rig(block: dict, description_dir: Path, timer=None, device: str = "cpu", renderer: str = "open3d"):
    """The rig of a job, built once per worker process (the Open3D scene and an EGL context cannot be
    pickled, so each process builds its own renderer) on ``device``, with the CPU ``renderer``; the first
    build is timed as ``setup``."""
    key = (str(description_dir), json.dumps(block, sort_keys=True), device, renderer)
    if key not in _PROCESS_CACHE:
        with timer("setup") if timer is not None else contextlib.nullcontext():
            rig = Rig.from_block(block, description_dir)
            rig.device = device
            rig.use_cpu_renderer(renderer)
            rig.renderer, rig.gripper  # noqa: B018 - built here, counted as setup
        _PROCESS_CACHE.clear()
        _PROCESS_CACHE[key] = rig
    return _PROCESS_CACHE[key]


def build_shard(job: ShardJob) -> Path:
    """Build one episode's shard dataset (idempotent: a finished shard is kept)."""
    if (job.shard_dir / INFO).is_file():
        return job.shard_dir
    raise_if_interrupted()
    pin_threads(job.threads)
    timer = StageTimer()
    wall, cpu = time.perf_counter(), time.process_time()
    rig = worker_rig(job.rig_block, job.description_dir, timer, job.device, job.settings.renderer)
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
    write_timings(job.timings_file, timer, episode=str(job.episode), threads=job.threads, pid=os.getpid(),
                  shard_wall_s=time.perf_counter() - wall, shard_cpu_s=time.process_time() - cpu,
                  peak_rss_mb=peak_rss_mb())
    return job.shard_dir


def _init_worker(threads: int, parent_pid: int) -> None:
    exit_with_parent(parent_pid)  # first: the imports below take seconds
    quiet_worker_interrupts()
    pin_threads(threads)
    quiet_libraries()


def run_jobs(jobs: list[ShardJob], *, executor: str, workers: int, ray_address: str | None,
             progress: bool) -> None:
    """Run the shard jobs that are not done yet: in this process (1 worker), a local
    process pool, or Ray tasks; each worker's thread pools pinned to ``job.threads``."""
    todo = [j for j in jobs if not (j.shard_dir / INFO).is_file()]
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
        else:
            run_local(build_shard, todo, workers=workers, threads=threads, done=lambda: bar.update(1))
    finally:
        bar.close()


def run_local(fn, items: list, *, workers: int, threads: int, done=None) -> None:
    """``fn(item)`` for every item (``fn`` a module-level function, ``items`` picklable) on ``workers``
    workers pulling from one queue: this process is one of them (its libraries are loaded already: a spawned
    worker first spends about 7 CPU-seconds on imports), the others are spawned pool processes with their
    thread pools pinned to ``threads``; ``done()`` after each item. Used for the shards and for the merge's
    groups, whose bytes do not depend on who makes them. Ctrl-C ends every worker; the first error is raised."""
    if workers <= 1 or len(items) <= 1:
        for item in items:
            fn(item)
            if done is not None:
                done()
        return
    workers = min(workers, len(items))
    jobs: queue.Queue = queue.Queue()
    for job in items:
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
            if done is not None:
                with lock:
                    done()

    saved = {k: os.environ.get(k) for k in thread_env(threads)}
    os.environ.update(thread_env(threads))  # pool workers size their pools at import
    try:
        with ProcessPoolExecutor(max_workers=workers - 1, mp_context=mp.get_context("spawn"), initializer=_init_worker,
                                 initargs=(threads, os.getpid())) as pool:
            remote = [threading.Thread(target=worker, args=(lambda j: pool.submit(run_as_job, fn, j).result(),))
                      for _ in range(workers - 1)]
            for t in remote:
                t.start()
            worker(fn, remote=False)  # this process works too
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
