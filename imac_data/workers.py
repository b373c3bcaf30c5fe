"""Build workers: how many, and each one's thread pools pinned to its share of the cores.

A worker builds whole episodes (:func:`imac_data.build.build_shard`). Its heavy parts all
run thread pools of their own: torch's OpenMP pool, OpenCV's, Embree's ray casting (the
renderer), the contact streams' Python threads and SciPy KD-tree queries, the SVT-AV1 and
x264 encoders. Left alone, each pool sizes itself to the whole machine, so two workers on
two cores run four-plus busy threads per core and a second worker made the build slower
(measured: 5.8 -> 5.0 frames/s). :func:`pin_threads` caps every pool at the worker's share.

None of these pools changes a result: the renderer, the contact streams and SVT-AV1 give
the same bytes with any thread count, and x264 (whose output does depend on its thread
count) runs with a fixed one (:meth:`~imac_data.dataset.videos.VideoEncoding.lossless_rgb`).
So a build's bytes do not depend on ``--workers``, the executor or the machine's cores
(``tests/test_build.py``: Ray with 2 workers = local with 1).
"""

from __future__ import annotations

import os

__all__ = ["cpu_cores", "default_workers", "threads_per_worker", "pin_threads", "thread_env"]

_THREAD_VARS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMEXPR_NUM_THREADS")


def cpu_cores() -> int:
    """Cores this process may run on (its affinity mask, else the machine's count)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def default_workers(episodes: int, cores: int | None = None) -> int:
    """``--workers`` when none is given: one worker per core, at most one per episode.

    Why (measured on a 2-core machine, ``benchmarks/run.py``, whole builds of the demo
    workload): with every worker's pools pinned to its share, one single-threaded worker
    per core gives the most frames/s per CPU-second; threads inside one process scale
    worse (the pipeline's serial parts: reading, metadata, the GIL between numpy calls)
    than whole episodes side by side. More workers than cores only add memory.
    """
    cores = cores or cpu_cores()
    return max(1, min(int(episodes), cores))


def threads_per_worker(workers: int, cores: int | None = None) -> int:
    return max(1, (cores or cpu_cores()) // max(1, int(workers)))


def thread_env(threads: int) -> dict[str, str]:
    """Environment for a new worker process: libraries that size their pools when loaded."""
    return {var: str(threads) for var in _THREAD_VARS}


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
