"""What the command-line entry points share: where outputs go, quiet libraries, exit codes.

Exit codes of every ``python -m imac_data.*`` command (:func:`run_command`):

* 0 success;
* 2 bad input (:class:`~imac_data.errors.InputError`): one message naming the file, key or field;
* 3 the environment (:class:`~imac_data.errors.EnvironmentFault`, or an ``OSError`` such as
  no space left, a read-only file system, no permission, a parent that is a file; another
  build holding the output's lock): one line saying what and where;
* 130 interrupted (Ctrl-C): one line, no traceback (the commands clean up as they unwind;
  a build keeps its finished episodes and resumes when rerun);
* 1 only for a bug (a traceback).
"""

from __future__ import annotations

import errno
import os
import sys
from collections.abc import Callable
from pathlib import Path

from imac_data.errors import EnvironmentFault, InputError

EXIT_OK, EXIT_BUG, EXIT_BAD_INPUT, EXIT_ENVIRONMENT = 0, 1, 2, 3
EXIT_INTERRUPTED = 130  # the shell's code for SIGINT

__all__ = ["default_root", "cache_home", "quiet_libraries", "silence_progress_bars", "run_command",
           "environment_problem", "EXIT_OK", "EXIT_BUG", "EXIT_BAD_INPUT", "EXIT_ENVIRONMENT",
           "EXIT_INTERRUPTED"]

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


def default_root(repo_id: str) -> Path:
    """Where LeRobot looks for ``repo_id``: ``$HF_LEROBOT_HOME/<repo_id>``."""
    from lerobot.utils.constants import HF_LEROBOT_HOME

    return Path(HF_LEROBOT_HOME) / repo_id


def cache_home() -> Path:
    return Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "imac"


def quiet_libraries() -> None:
    """Keep the console to our progress bars: SVT-AV1 banners, libav muxer notes and
    the datasets library's per-file bars say nothing a user acts on."""
    os.environ.setdefault("SVT_LOG", "1")  # SVT-AV1: errors only
    import av
    import datasets

    av.logging.set_level(av.logging.ERROR)
    datasets.disable_progress_bars()


def silence_progress_bars() -> None:
    """``--no-progress``: no bar at all, LeRobot's own included (its ``aggregate_datasets``
    and dataset tools draw tqdm bars of their own). tqdm reads ``TQDM_DISABLE`` when it is
    imported, so the variable covers worker processes; in this process tqdm is usually
    imported already and gets the same default applied here."""
    import functools

    os.environ.update(TQDM_DISABLE="1", HF_DATASETS_DISABLE_PROGRESS_BARS="1", HF_HUB_DISABLE_PROGRESS_BARS="1")
    import datasets
    import huggingface_hub.utils
    import tqdm.std

    datasets.disable_progress_bars()
    huggingface_hub.utils.disable_progress_bars()
    if not getattr(tqdm.std.tqdm, "_imac_silenced", False):  # what TQDM_DISABLE=1 does at import
        tqdm.std.tqdm.__init__ = functools.partialmethod(tqdm.std.tqdm.__init__, disable=True)
        tqdm.std.tqdm._imac_silenced = True


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
    """A one-line description of ``exc`` if the environment caused it (an ``OSError`` with
    an errno of :data:`_ENVIRONMENT_ERRNOS` anywhere in its chain, also when a library
    re-raised it with only the message kept), else None."""
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


INTERRUPTED = "interrupted (a build keeps its finished episodes: rerun the same command to resume)"


def quiet_startup_interrupts() -> None:
    """Ctrl-C while ``python -m imac_data.<command>`` loads its libraries (seconds: torch),
    before :func:`run_command` takes over: the one line and 130, not a traceback from deep
    inside an import. Nothing is written yet, so the process just ends."""
    import signal

    def handler(signum, frame) -> None:
        print(INTERRUPTED, file=sys.stderr, flush=True)
        os._exit(EXIT_INTERRUPTED)

    signal.signal(signal.SIGINT, handler)


def exit_process(code: int) -> None:
    """End a command-line process with ``code`` (``sys.exit`` at the bottom of each CLI
    module). After Ctrl-C the process ends at once, flushed, without Python's shutdown: a
    native library interrupted while loading (Open3D: ``ImportError: initialization
    failed``) runs exit handlers that turn the status into 1. Cleanup already ran as the
    stack unwound; the output's lock is the kernel's to drop."""
    if code == EXIT_INTERRUPTED:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    sys.exit(code)


def run_command(body: Callable[[], int | None]) -> int:
    """Run a command's body with the shared exit codes (module docstring): bad input and
    environment faults print one ``error:`` line (the message) and return 2 or 3, Ctrl-C one
    line and 130; anything else is a bug and propagates with its traceback."""
    from imac_data.workers import interrupt_pending, note_interrupts

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
