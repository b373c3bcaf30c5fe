"""How a command runs: the cores it may use, quiet libraries, exit codes, one-line errors, Ctrl-C.

Every ``imac`` command runs its body through :func:`run_command`. Exit codes:
0 success, 2 bad input (:class:`~imac_data.errors.InputError`), 3 the environment
(:class:`~imac_data.errors.EnvironmentFault` or an ``OSError`` such as no space left),
130 Ctrl-C (one line, wherever it lands), 1 a bug (a traceback). ``docs/building.md``
explains the Ctrl-C design: worker processes, libraries that swallow the interrupt.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import errno
import functools
import os
import signal
import sys
import threading
import warnings
from collections.abc import Callable

from imac_data.errors import EnvironmentFault, InputError

EXIT_OK, EXIT_BUG, EXIT_BAD_INPUT, EXIT_ENVIRONMENT = 0, 1, 2, 3
EXIT_INTERRUPTED = 130  # the shell's code for SIGINT
INTERRUPTED = "interrupted (a build keeps its finished episodes: rerun the same command to resume)"

__all__ = ["cpu_cores", "limit_malloc_arenas", "release_freed_memory", "run_command", "exit_process",
           "environment_problem", "interrupted", "quiet_libraries",
           "silence_progress_bars", "quiet_startup_interrupts", "note_interrupts", "interrupt_pending",
           "raise_if_interrupted", "block_interrupts_in_this_thread", "quiet_worker_interrupts", "run_as_job",
           "native_stderr_silenced", "allow_realtime", "realtime_refused", "refuse_realtime", "restore_scheduling",
           "scheduling", "scheduling_kept",
           "EXIT_OK", "EXIT_BUG", "EXIT_BAD_INPUT", "EXIT_ENVIRONMENT", "EXIT_INTERRUPTED", "INTERRUPTED"]

# errno -> what the user can do about it
_ENVIRONMENT_ERRNOS = {
    errno.ENOSPC: "free some space and rerun: finished episodes stay in staging, so the build resumes",
    errno.EDQUOT: "free some space or raise the quota and rerun: the build resumes",
    errno.EROFS: "the file system is read-only: choose another output",
    errno.EACCES: "check the permissions of that path",
    errno.EPERM: "check the permissions of that path",
    errno.ENOTDIR: "a parent of that path is a file, not a directory",
    errno.EMFILE: "raise the open-file limit (ulimit -n)",
    errno.ENFILE: "the system ran out of open files",
    errno.EIO: "the disk reported an I/O error",
}
_BY_TEXT = (errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES)  # unambiguous enough to find in a message


# ----------------------------------------------------------------------------- the machine


def cpu_cores() -> int:
    """Cores this process may run on (its affinity mask, else the machine's count)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


# ----------------------------------------------------------------------------- libraries


@functools.cache
def _libc():
    try:
        return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    except OSError:
        return None


# glibc gives every allocating thread its own malloc arena and keeps freed memory in it: one
# arena, set before a build's threads allocate, keeps a worker's peak down (docs/building.md).
MALLOC_ARENAS = 1
_M_ARENA_MAX = -8  # mallopt parameter (glibc malloc.h)


def limit_malloc_arenas() -> None:
    """At most :data:`MALLOC_ARENAS` glibc malloc arenas from now on (no-op elsewhere).
    Threads that already have an arena keep it: call it before they start."""
    mallopt = getattr(_libc(), "mallopt", None)
    if mallopt is not None:
        mallopt(_M_ARENA_MAX, MALLOC_ARENAS)


def release_freed_memory() -> None:
    """Give the memory that glibc's malloc keeps after frees back to the system (``malloc_trim``; a no-op
    without glibc). Called between a build's chunks: without it a worker's resident memory crept up with
    the episode's length, freed chunks kept in its heap (docs/building.md, "Workers, memory and speed")."""
    libc = _libc()
    trim = getattr(libc, "malloc_trim", None)
    if trim is not None:
        trim(0)


def quiet_libraries() -> None:
    """Keep the console to our progress bars: SVT-AV1 banners, libav muxer notes and the
    datasets library's per-file bars say nothing a user acts on."""
    import av
    import datasets

    os.environ.setdefault("SVT_LOG", "1")  # SVT-AV1: errors only
    av.logging.set_level(av.logging.ERROR)
    datasets.disable_progress_bars()


_BARS_WARNING = "Cannot enable progress bars"


def silence_progress_bars() -> None:
    """``--no-progress``: no bar at all, LeRobot's own included. tqdm reads ``TQDM_DISABLE``
    when imported, which covers worker processes; here tqdm is usually loaded already."""
    import datasets
    import huggingface_hub.utils
    import tqdm.std

    os.environ.update(TQDM_DISABLE="1", HF_DATASETS_DISABLE_PROGRESS_BARS="1", HF_HUB_DISABLE_PROGRESS_BARS="1")
    # LeRobot re-enables datasets' bars after each parquet load; with the variable set, datasets warns each time
    quiet = f"ignore:{_BARS_WARNING}:UserWarning"
    warnings.filterwarnings("ignore", message=_BARS_WARNING, category=UserWarning)
    if quiet not in os.environ.get("PYTHONWARNINGS", "").split(","):  # and in the processes started from here
        os.environ["PYTHONWARNINGS"] = ",".join(filter(None, [os.environ.get("PYTHONWARNINGS"), quiet]))
    datasets.disable_progress_bars()
    huggingface_hub.utils.disable_progress_bars()
    if not getattr(tqdm.std.tqdm, "_imac_silenced", False):  # what TQDM_DISABLE=1 does at import
        tqdm.std.tqdm.__init__ = functools.partialmethod(tqdm.std.tqdm.__init__, disable=True)
        tqdm.std.tqdm._imac_silenced = True


# ----------------------------------------------------------------------------- errors


def _chain(exc: BaseException | None):
    """``exc`` and the exceptions it was raised from or while handling, newest first."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        yield exc
        exc = exc.__cause__ or exc.__context__


def interrupted(exc: BaseException) -> bool:
    """Whether Ctrl-C caused ``exc``: a ``KeyboardInterrupt`` anywhere in its chain (a native
    import interrupted half-way re-raises it as ``ImportError: initialization failed``)."""
    return any(isinstance(e, KeyboardInterrupt) for e in _chain(exc))


def environment_problem(exc: BaseException) -> str | None:
    """One line describing ``exc`` if the machine caused it (an errno of
    :data:`_ENVIRONMENT_ERRNOS` anywhere in its chain, also when only the message kept it)."""
    for exc in _chain(exc):
        if isinstance(exc, EnvironmentFault):
            return str(exc)
        code = getattr(exc, "errno", None) if isinstance(exc, OSError) else None
        if code not in _ENVIRONMENT_ERRNOS:  # pyarrow, PyAV: errno lost, strerror kept in the text
            code = next((c for c in _BY_TEXT if os.strerror(c) in str(exc)), None)
        if code is not None:
            where = getattr(exc, "filename", None)
            return (f"{os.strerror(code)} ({errno.errorcode[code]}){f': {where}' if where else ''} - "
                    f"{_ENVIRONMENT_ERRNOS[code]}")
    return None


def run_command(body: Callable[[], int | None]) -> int:
    """Run a command's body with the exit codes above: bad input and environment faults print
    one ``error:`` line, Ctrl-C one line; anything else is a bug and keeps its traceback."""
    note_interrupts()
    try:
        code = body()
    except InputError as e:
        print(f"error: {e}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except (KeyboardInterrupt, Exception) as e:
        if interrupted(e) or interrupt_pending():  # an error that a Ctrl-C caused, however wrapped
            print(INTERRUPTED, file=sys.stderr)
            return EXIT_INTERRUPTED
        problem = environment_problem(e)
        if problem is None:
            raise
        print(f"error: {problem}", file=sys.stderr)
        return EXIT_ENVIRONMENT
    return EXIT_OK if code is None else code


def exit_process(code: int) -> None:
    """End a command-line process. After Ctrl-C it ends at once, without Python's shutdown: a
    native library interrupted while loading (Open3D) runs exit handlers that turn 130 into 1.
    Cleanup already ran as the stack unwound."""
    if code == EXIT_INTERRUPTED:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    sys.exit(code)


# ----------------------------------------------------------------------------- Ctrl-C
# A terminal's Ctrl-C reaches every process of the group: the command reports it in one line,
# its pool workers stay quiet. Some libraries swallow the KeyboardInterrupt (trimesh's optional
# imports catch BaseException), so the handlers also record it and long loops poll
# raise_if_interrupted.
_in_job = False
_interrupt_pending = False


def quiet_startup_interrupts() -> None:
    """Ctrl-C while a command still loads its libraries (seconds: torch): the one line and 130,
    not a traceback from deep inside an import. Nothing is written yet, so the process just ends."""
    def handler(signum, frame) -> None:
        print(INTERRUPTED, file=sys.stderr, flush=True)
        os._exit(EXIT_INTERRUPTED)

    signal.signal(signal.SIGINT, handler)


def _command_interrupt(signum, frame) -> None:
    global _interrupt_pending
    _interrupt_pending = True
    raise KeyboardInterrupt


def note_interrupts() -> None:
    """In a command's main thread: Ctrl-C raises KeyboardInterrupt as usual and is recorded, so
    that one a library swallowed still stops the command (:func:`raise_if_interrupted`)."""
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
    """Hold SIGINT in the calling (non-main) thread, and so in the processes it starts: a
    spawned worker then starts with it held until :func:`quiet_worker_interrupts`."""
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})


def _silence_native_stderr() -> None:
    """fd 2 to /dev/null: as a job unwinds after Ctrl-C, native libraries still write there (an
    SVT-AV1 encoder freed mid-stream: "deinit called without sending EOS!"); the command reports."""
    sys.stderr.flush()
    null = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(null, 2)
    finally:
        os.close(null)


@contextlib.contextmanager
def native_stderr_silenced():
    """fd 2 to /dev/null for the block, then back: for a native call whose message says nothing
    to the user (an aborted encoder's complaint that it was freed before its stream ended)."""
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        _silence_native_stderr()
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def scheduling() -> tuple[int, int] | None:
    """This thread's CPU scheduling, (policy, priority); None where the OS has no such call (not Linux)."""
    if not hasattr(os, "sched_getscheduler"):
        return None
    return os.sched_getscheduler(0), os.sched_getparam(0).sched_priority


def restore_scheduling(saved: tuple[int, int] | None) -> None:
    """Put back what :func:`scheduling` returned, if it changed (lowering one's own needs no privilege)."""
    if saved is not None and scheduling() != saved:
        os.sched_setscheduler(0, saved[0], os.sched_param(saved[1]))


# A thread's Linux capabilities (capget/capset, <linux/capability.h>): version 3, two 32-bit words per set.
_CAP_VERSION_3, _CAP_SYS_NICE = 0x20080522, 23


class _CapHeader(ctypes.Structure):
    _fields_ = [("version", ctypes.c_uint32), ("pid", ctypes.c_int)]


class _CapData(ctypes.Structure):
    _fields_ = [("effective", ctypes.c_uint32), ("permitted", ctypes.c_uint32), ("inheritable", ctypes.c_uint32)]


def _thread_capabilities():
    """This thread's capability sets (two :class:`_CapData` words), or None where there is no capget."""
    capget = getattr(_libc(), "capget", None)
    data = (_CapData * 2)()
    if capget is None or capget(ctypes.byref(_CapHeader(_CAP_VERSION_3, 0)), data) != 0:
        return None
    return data


def _set_thread_capabilities(data) -> bool:
    capset = getattr(_libc(), "capset", None)
    return capset is not None and capset(ctypes.byref(_CapHeader(_CAP_VERSION_3, 0)), data) == 0


def refuse_realtime():
    """From now on this thread, and every thread it starts, may not make itself real-time: CAP_SYS_NICE leaves
    the thread's effective capabilities (a program it executes gets them back as root). Returns what
    :func:`allow_realtime` puts back, or None where the thread lacked the capability or the OS has none."""
    caps = _thread_capabilities()
    if caps is None or not caps[0].effective >> _CAP_SYS_NICE & 1:
        return None
    lowered = (_CapData * 2)(*(_CapData(c.effective, c.permitted, c.inheritable) for c in caps))
    lowered[0].effective &= ~(1 << _CAP_SYS_NICE)
    return caps if _set_thread_capabilities(lowered) else None


def allow_realtime(saved) -> None:
    """Put back what :func:`refuse_realtime` took (from the permitted set, which it never lowered)."""
    if saved is not None:
        _set_thread_capabilities(saved)


@contextlib.contextmanager
def realtime_refused():
    """:func:`refuse_realtime` for the block. SVT-AV1 (LeRobot's camera codec), run as root, makes the thread
    that opens an encoder and every encoder thread SCHED_FIFO at priority 99; refused, it encodes the same bytes
    at normal priority (docs/building.md, "Real-time scheduling left by the AV1 encoder")."""
    saved = refuse_realtime()
    try:
        yield
    finally:
        allow_realtime(saved)


@contextlib.contextmanager
def scheduling_kept():
    """An encoder's block: no thread made real-time in it (:func:`realtime_refused`), and this thread's CPU
    scheduling put back after it where something made it so all the same. A real-time encoder thread starves
    every other process of a 2-core machine, and a real-time caller passes its policy to every process it
    starts (docs/building.md, "Real-time scheduling left by the AV1 encoder")."""
    saved = scheduling()
    try:
        with realtime_refused():
            yield
    finally:
        restore_scheduling(saved)


def _worker_interrupt(signum, frame) -> None:
    global _interrupt_pending
    _interrupt_pending = True
    _silence_native_stderr()
    if _in_job:  # the job cleans up as it unwinds; the pool hands the exception to the build
        raise KeyboardInterrupt
    os._exit(EXIT_INTERRUPTED)  # idle: nothing to clean up, and no traceback from the pool's loop


def quiet_worker_interrupts() -> None:
    """In a pool worker: Ctrl-C interrupts a running job (:func:`run_as_job`) and ends an idle
    worker without a traceback; a Ctrl-C held while the worker started arrives now."""
    signal.signal(signal.SIGINT, _worker_interrupt)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})


def run_as_job(fn, *args):
    """``fn(*args)`` in a pool worker, marked as a job that Ctrl-C interrupts (and cleans up)."""
    global _in_job
    _in_job = True
    try:
        return fn(*args)
    finally:
        _in_job = False
