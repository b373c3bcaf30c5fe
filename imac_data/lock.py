"""One writer per output: an OS file lock next to the output's staging directory.

A build (or an augmentation) of ``ROOT`` holds ``fcntl.flock`` on ``.ROOT.lock`` beside
``ROOT`` for as long as it writes the staging directory or swaps the result into place.
The lock file lies next to the staging directory, not inside it, because staging is
deleted when the build key changes. A second writer of the same output refuses with an
:class:`~imac_data.errors.EnvironmentFault` naming the holder's PID (exit 3), or waits
for it (``wait=True``, ``--wait``). The kernel drops the lock when its holder dies, so a
killed build never leaves a stale lock; the file itself is removed on release.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import sys
from collections.abc import Iterator
from pathlib import Path

from imac_data.errors import EnvironmentFault

__all__ = ["lock_path", "output_lock"]


def lock_path(root: Path) -> Path:
    from imac_data.safety import output_sibling

    return output_sibling(root, "lock")


def _holder(path: Path) -> str:
    try:
        return path.read_text().strip() or "unknown"
    except OSError:
        return "unknown"


def _same_file(path: Path, fd: int) -> bool:
    try:
        return os.stat(path).st_ino == os.fstat(fd).st_ino
    except FileNotFoundError:
        return False


def _acquire(path: Path, root: Path, wait: bool) -> int:
    """A descriptor of ``path`` holding its exclusive lock. The previous holder may unlink the
    file between our open and our lock: then the lock is on a dead inode, so try again."""
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                pid = _holder(path)
                if not wait:
                    raise EnvironmentFault(
                        f"another build (PID {pid}) is writing {root} (it holds {path}); wait for it to finish, "
                        "or pass --wait") from None
                print(f"[lock] waiting for the build with PID {pid} to release {root}", file=sys.stderr)
                fcntl.flock(fd, fcntl.LOCK_EX)
            if _same_file(path, fd):
                return fd
        except BaseException:
            os.close(fd)
            raise
        os.close(fd)


@contextlib.contextmanager
def output_lock(root: Path, *, wait: bool = False) -> Iterator[Path]:
    """Hold the lock of output ``root`` (:func:`lock_path`) for the ``with`` block."""
    path = lock_path(root)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = _acquire(path, Path(root), wait)
    try:
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        yield path
    finally:
        with contextlib.suppress(OSError):
            os.unlink(path)  # while still holding it: a waiter then retries on a fresh file
        os.close(fd)
