"""Build workers: how many, and each one's thread pools pinned to its share of the cores.

Memory: a worker holds one chunk of one episode at a time (:mod:`imac_data.pipeline`);
what else it holds is its libraries (about 0.8 GB), the rig (0.2 GB) and the video
encoders' buffers (about 0.3 GB at 240x320, 0.8 GB at 480x640 for the 15 streams).

A worker builds whole episodes (:func:`imac_data.build.build_shard`). Its heavy parts all
run thread pools of their own: torch's OpenMP pool, OpenCV's, Embree's ray casting (the
renderer), the contact streams' Python threads and their KD-tree queries, the SVT-AV1 and
x264 encoders. Left alone, each pool sizes itself to the whole machine, so two workers on
two cores run four-plus busy threads per core and a second worker made the build slower
(measured: 5.8 -> 5.0 frames/s). :func:`pin_threads` caps every pool at the worker's share.

None of these pools changes a result: the renderer, the contact streams and SVT-AV1 give
the same bytes with any thread count, and x264 (whose output does depend on its thread
count) runs with a fixed one (:meth:`~imac_data.dataset.videos.VideoEncoding.lossless_rgb`).
So a build's bytes do not depend on ``--workers``, the executor or the machine's cores
(``tests/test_build.py``: Ray with 2 workers = local with 1).

A pool worker dies with the build that started it (:func:`exit_with_parent`), so no
orphan keeps writing into the staging directory after the build was killed.
"""

from __future__ import annotations

import os

__all__ = ["cpu_cores", "default_workers", "threads_per_worker", "pin_threads", "thread_env", "peak_rss_mb",
           "exit_with_parent", "limit_malloc_arenas"]

_THREAD_VARS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMEXPR_NUM_THREADS")
# glibc gives each thread that allocates its own malloc arena and keeps freed memory in it;
# with the pipeline's encoder and contact threads that alone added about 0.4 GB to a
# 480x640 worker (measured: 3.16 -> 2.78 GB peak with 2 threads, two arenas). One arena,
# set before the rig's threads first allocate, takes another 50-100 MB off (100- and
# 400-frame episodes at 480x640) and costs no measurable time.
_MALLOC_ARENAS = 1
_M_ARENA_MAX = -8  # mallopt parameter (glibc malloc.h)


def cpu_cores() -> int:
    """Cores this process may run on (its affinity mask, else the machine's count)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def default_workers(episodes: int, cores: int | None = None) -> int:
    """``--workers`` when none is given: one worker per core, at most one per episode.

    Why (measured on a 2-core machine with whole builds of the benchmark's 4 recorded
    episodes, 498 frames, 1 and 2 workers alternated, 3 rounds each): the CPU per frame
    is the same (211 vs 210 ms), and 2 workers had the higher frames/s in 2 of 3 rounds
    (7.97 vs 7.56 mean). Threads inside one worker scale worse than whole episodes side
    by side (the pipeline's serial numpy between the threaded calls: about 1.6 of 2 cores
    busy vs 1.8), and that gain pays for a spawned worker's imports (about 7 CPU-seconds,
    torch, LeRobot, Open3D), which larger builds amortise further. At 480x640, 2 workers
    were 1.01-1.13x faster. More workers than cores only add memory.
    """
    cores = cores or cpu_cores()
    return max(1, min(int(episodes), cores))


def threads_per_worker(workers: int, cores: int | None = None) -> int:
    return max(1, (cores or cpu_cores()) // max(1, int(workers)))


def thread_env(threads: int) -> dict[str, str]:
    """Environment for a new worker process: libraries that size their pools when loaded,
    and glibc's malloc arenas."""
    return {**{var: str(threads) for var in _THREAD_VARS}, "MALLOC_ARENA_MAX": str(_MALLOC_ARENAS)}


def pin_threads(threads: int) -> None:
    """Cap this process's thread pools at ``threads`` (torch, OpenCV; the renderer, contact
    queries and encoders take theirs from the rig / pipeline settings)."""
    import cv2
    import torch

    threads = max(1, int(threads))
    for var, value in thread_env(threads).items():
        os.environ[var] = value  # for anything loaded later (and child processes)
    torch.set_num_threads(threads)
    cv2.setNumThreads(threads)
    limit_malloc_arenas()


def limit_malloc_arenas() -> None:
    """At most :data:`_MALLOC_ARENAS` glibc malloc arenas from now on (no-op elsewhere).
    Threads that already have an arena keep it: call it before they start."""
    import ctypes
    import ctypes.util

    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        libc.mallopt(_M_ARENA_MAX, _MALLOC_ARENAS)
    except (OSError, AttributeError):
        pass


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
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


# --- Ctrl-C ----------------------------------------------------------------------------------------
# A terminal's Ctrl-C reaches every process of the group. The build process reports it in one
# line; its pool workers must stay quiet. A spawned worker spends seconds importing before any
# code of ours runs in it, so the threads that start workers block SIGINT (the mask is
# inherited: the new process starts with SIGINT held), and quiet_worker_interrupts, run by the
# pool's initializer, installs the worker's handler and releases what was held.
# Some libraries swallow the KeyboardInterrupt (trimesh wraps its optional imports in
# ``except BaseException``), so both handlers also record it, and the pipeline stops at the
# next chunk (raise_if_interrupted).
_in_job = False
_interrupt_pending = False


def _command_interrupt(signum, frame) -> None:
    global _interrupt_pending
    _interrupt_pending = True
    raise KeyboardInterrupt


def note_interrupts() -> None:
    """In a command's main thread: Ctrl-C raises KeyboardInterrupt as usual and is recorded, so
    that one a library swallowed still stops the command (:func:`raise_if_interrupted`)."""
    import signal
    import threading

    global _interrupt_pending
    _interrupt_pending = False
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, _command_interrupt)


def interrupt_pending() -> bool:
    """Whether Ctrl-C reached this process (see :func:`note_interrupts`)."""
    return _interrupt_pending


def raise_if_interrupted() -> None:
    """KeyboardInterrupt if Ctrl-C reached this process, even if a library swallowed it."""
    if _interrupt_pending:
        raise KeyboardInterrupt


def block_interrupts_in_this_thread() -> None:
    """Hold SIGINT in the calling (non-main) thread, and so in the processes it starts."""
    import signal

    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})


def _worker_interrupt(signum, frame) -> None:
    global _interrupt_pending
    _interrupt_pending = True
    if _in_job:  # the job cleans up as it unwinds; the pool hands the exception to the build
        raise KeyboardInterrupt
    os._exit(130)  # idle: nothing to clean up, and no traceback from the pool's loop


def quiet_worker_interrupts() -> None:
    """In a pool worker: Ctrl-C interrupts a running job (see :func:`run_as_job`) and ends an
    idle worker without a traceback."""
    import signal

    signal.signal(signal.SIGINT, _worker_interrupt)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})  # a Ctrl-C held during start-up arrives now


def run_as_job(fn, *args):
    """``fn(*args)`` in a pool worker, marked as a job that Ctrl-C interrupts (and cleans up)."""
    global _in_job
    _in_job = True
    try:
        return fn(*args)
    finally:
        _in_job = False


def exit_with_parent(parent_pid: int, interval_s: float = 0.2) -> None:
    """Kill this process as soon as its parent ``parent_pid`` is gone (the orphan is
    re-parented, so ``getppid`` changes), from a daemon thread that polls every ``interval_s``.

    Why not ``prctl(PR_SET_PDEATHSIG)``: Linux sends that signal when the *thread* that
    started the process ends, and a process pool starts its workers from whichever thread
    submits first (the build's feeder threads, which end before the pool does), so it
    would kill live workers. The poll costs nothing measurable."""
    import signal
    import threading
    import time

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(interval_s)
        os.kill(os.getpid(), signal.SIGKILL)

    threading.Thread(target=watch, name="exit-with-parent", daemon=True).start()
