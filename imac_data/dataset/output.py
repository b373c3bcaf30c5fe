"""Where a build writes, and what protects the user's data.

A build of ``ROOT`` writes ``ROOT`` and three siblings: ``.ROOT.staging`` (where the dataset
is assembled), ``.ROOT.old`` (the previous output, kept until the new one is in place) and
``.ROOT.lock`` (one writer at a time). Before any work:

* an output that is, contains or lies inside an input is refused (:func:`refuse_overlap`);
* an existing output is replaced only with ``--overwrite`` and only when it is a dataset, and
  a sibling path is deleted only when it is ours (:func:`check_output`, :func:`check_sibling`);
* a disk that plainly cannot hold the build gets a warning (:func:`warn_if_short_of_space`).

``docs/building.md`` lists each guarantee with the test that checks it.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import shutil
import sys
from collections.abc import Iterator, Mapping
from pathlib import Path

from imac_data.errors import EnvironmentFault, InputError
from imac_data.layout import INFO

__all__ = ["output_sibling", "staging_dir", "make_sibling_dir", "check_sibling", "remove_sibling", "swap_into_place",
           "refuse_overlap", "check_replaceable", "check_output", "lock_path", "output_lock", "estimate_build_bytes",
           "free_bytes", "warn_if_short_of_space", "SIBLING_MARKER"]


def _real(path: Path) -> Path:
    # resolve() follows symlinks, so a link to the source counts as the source
    return Path(path).expanduser().resolve()


def _is_within(inner: Path, outer: Path) -> bool:
    return inner == outer or outer in inner.parents


SIBLING_SUFFIXES = ("staging", "old", "lock")


def output_sibling(root: Path, suffix: str) -> Path:
    """``.<name>.<suffix>`` next to the output ``root`` (one of :data:`SIBLING_SUFFIXES`):
    where it is staged, locked or kept while it is replaced. ``root`` is made absolute first:
    ``.`` or ``x/..`` have no name of their own. abspath, not resolve: a symlinked root stays
    a symlink for the overlap checks."""
    if suffix not in SIBLING_SUFFIXES:
        raise ValueError(f"unknown output sibling {suffix!r}")
    root = Path(os.path.abspath(root))
    return root.parent / f".{root.name}.{suffix}"


def staging_dir(root: Path) -> Path:
    """Where a dataset for ``root`` is assembled before it is moved into place."""
    return output_sibling(root, "staging")


# Written into the staging directories we make (removed before a staged copy becomes the output),
# so that a leftover one is known to be ours.
SIBLING_MARKER = ".imac-sibling"
_OWNED_BY = (SIBLING_MARKER, "BUILD_KEY", INFO)  # BUILD_KEY: build staging of earlier versions


def make_sibling_dir(path: Path) -> Path:
    """Create the staging directory ``path`` (an :func:`output_sibling`) with our marker in it."""
    path.mkdir(parents=True)
    (path / SIBLING_MARKER).write_text("staged by imac_data; safe to delete\n")
    return path


def check_sibling(path: Path) -> None:
    """Refuse (:class:`InputError`) to delete the :func:`output_sibling` ``path`` unless it is
    absent or ours: an empty directory, one with our marker (or a build key), or a LeRobot
    dataset (an output kept while it is replaced). A directory of the user's that happens to
    have that name is never deleted."""
    if not (path.exists() or path.is_symlink()):
        return
    if path.is_dir() and not path.is_symlink():
        if not any(path.iterdir()) or any((path / name).is_file() for name in _OWNED_BY):
            return
    raise InputError(f"{path} exists and was not made by imac_data (no {SIBLING_MARKER} marker, not a LeRobot "
                     "dataset): writing the output next to it stages or keeps data at that path and would delete it. "
                     "Move it away or choose another output")


def swap_into_place(new: Path, root: Path, *, old_suffix: str = "old") -> None:
    """Rename the complete dataset ``new`` to ``root``. An existing ``root`` (``--overwrite``,
    or the dataset an in-place edit replaces) is kept as ``.<name>.<old_suffix>`` until the
    rename succeeds, put back if it fails, then deleted."""
    old = output_sibling(root, old_suffix)
    remove_sibling(old)
    if root.exists():
        root.rename(old)
    try:
        root.parent.mkdir(parents=True, exist_ok=True)
        new.rename(root)
    except BaseException:
        if old.exists():
            old.rename(root)
        raise
    shutil.rmtree(old, ignore_errors=True)


def remove_sibling(path: Path) -> None:
    """Delete the leftover :func:`output_sibling` ``path`` after :func:`check_sibling`."""
    check_sibling(path)
    if path.exists():
        shutil.rmtree(path)


def output_neighbours(root: Path) -> list[Path]:
    """Every path a build or an augmentation of ``root`` may create, replace or delete."""
    return [Path(os.path.abspath(root))] + [output_sibling(root, suffix) for suffix in SIBLING_SUFFIXES]


def refuse_overlap(output: Path, inputs: Mapping[str, Path | None], *, what: str = "--root") -> None:
    """Raise :class:`InputError` if the output ``output`` (and the paths written next to it,
    :func:`output_neighbours`) is, contains or lies inside any of ``inputs``.

    ``inputs``: a description (``"source episodes"``, ``"calibration"``) -> path (a file or
    a directory; ``None`` entries are skipped). Writing *next to* an input is fine; the
    output may not enclose an input (``--overwrite`` would delete it) nor be inside an
    input directory (the user's recording directory is not ours to write into).
    """
    written = [_real(p) for p in output_neighbours(output)]
    for name, path in inputs.items():
        if path is None:
            continue
        src = _real(path)
        for w in written:
            if _is_within(src, w):
                raise InputError(
                    f"{what} {output} would contain the {name} {path}: building there could overwrite or delete "
                    f"it. Choose an output directory outside {path}")
            if src.is_dir() and _is_within(w, src):
                raise InputError(
                    f"{what} {output} lies inside the {name} directory {path}: the source is only read, "
                    f"never written. Choose an output directory outside {path}")


def check_replaceable(path: Path, *, made_by: str, what: str) -> None:
    """Refuse (:class:`InputError`) to let ``--overwrite`` replace ``path`` unless it is absent,
    an empty directory, or a directory holding ``made_by`` (the file every such output of
    ours has: a QA ``summary.json``, a calibration ``report.json``)."""
    path = Path(path)
    if not (path.exists() or path.is_symlink()):
        return
    if not path.is_dir() or path.is_symlink():
        raise InputError(f"{what} {path} exists and is not a directory; --overwrite replaces only an output of ours")
    if any(path.iterdir()) and not (path / made_by).is_file():
        raise InputError(f"{what} {path} is a directory without {made_by}, so not an output of this command: "
                         "--overwrite would delete it. Choose another output")


def check_output(root: Path, *, overwrite: bool, what: str = "--root") -> None:
    """Refuse an output that may not be replaced, or cannot be made, before any work starts.

    An existing ``root`` is replaced only with ``overwrite``, and only when it is a LeRobot
    dataset (``meta/info.json``) or an empty directory: never a file nor someone's other
    directory (:class:`InputError`). The staging and ``.old`` paths next to it must be absent
    or ours (:func:`check_sibling`). The nearest existing ancestor must be a directory this
    process may write (else :class:`~imac_data.errors.EnvironmentFault`).
    """
    root = Path(root)
    for suffix in ("staging", "old"):  # a build deletes leftovers there
        check_sibling(output_sibling(root, suffix))
    if root.exists() or root.is_symlink():
        if not overwrite:
            raise InputError(f"output {root} already exists; pass --overwrite to replace it")
        if not root.is_dir():
            raise InputError(f"{what} {root} is a file, not a dataset: --overwrite replaces only a LeRobot dataset "
                             "directory. Remove the file yourself or choose another output")
        if any(root.iterdir()) and not (root / INFO).is_file():
            raise InputError(f"{what} {root} is a directory but not a LeRobot dataset (no meta/info.json): "
                             "--overwrite replaces only a dataset. Choose another output")
        cwd = Path.cwd().resolve()
        if cwd.is_relative_to(root.resolve()):
            raise InputError(f"{what} {root} is (or contains) the current directory {cwd}: replacing it would delete "
                             "the directory this command runs in. Run it from outside the dataset")
    parent = root.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise EnvironmentFault(f"cannot create {what} {root}: {parent} is a file, not a directory")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise EnvironmentFault(f"cannot write {what} {root}: {parent} is read-only or not writable by this user")


# ----------------------------------------------------------------------------- one writer per output


def lock_path(root: Path) -> Path:
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


def _acquire(path: Path, root: Path, wait: bool, who: str = "build",
             hint: str = "wait for it to finish, or pass --wait") -> int:
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
                    raise EnvironmentFault(f"another {who} (PID {pid}) is writing {root} (it holds {path}); {hint}") \
                        from None
                print(f"[lock] waiting for the {who} with PID {pid} to release {root}", file=sys.stderr)
                fcntl.flock(fd, fcntl.LOCK_EX)
            if _same_file(path, fd):
                return fd
        except BaseException:
            os.close(fd)
            raise
        os.close(fd)


def lock_holder(root: Path) -> str | None:
    """The PID of the process that holds ``root``'s lock now, or None. It holds a shared lock for an instant
    only, and never waits."""
    try:
        fd = os.open(lock_path(root), os.O_RDONLY | os.O_CLOEXEC)
    except FileNotFoundError:
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        fcntl.flock(fd, fcntl.LOCK_UN)
        return None
    except BlockingIOError:
        return _holder(lock_path(root))
    finally:
        os.close(fd)


@contextlib.contextmanager
def output_lock(root: Path, *, wait: bool = False, who: str = "build",
                hint: str = "wait for it to finish, or pass --wait") -> Iterator[Path]:
    """Hold the lock of output ``root`` (:func:`lock_path`) for the ``with`` block; ``who`` and
    ``hint`` word the refusal when another process holds it."""
    path = lock_path(root)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = _acquire(path, Path(root), wait, who, hint)
    try:
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        yield path
    finally:
        with contextlib.suppress(OSError):
            os.unlink(path)  # while still holding it: a waiter then retries on a fresh file
        os.close(fd)


# ----------------------------------------------------------------------------- free space
# A build's staging holds every shard and the merged copy of them at once: about twice the output; three times
# when the merge is a tree (merge.py), whose last call reads a level while it writes the output.
# The output is bounded below from its pixels: the 15 encoded streams took 0.14-0.22 bytes per pixel
# and frame on our simulated datasets; a third of the lower figure warns only when the output plainly
# will not fit.
BYTES_PER_PIXEL = 0.05
STREAMS_PER_CAMERA = 4  # depth, motion, contact r2s, contact s2g (beside the recorded RGB)


def estimate_build_bytes(total_frames: int, image_hw: dict[str, tuple[int, int]], stream_hw: tuple[int, int],
                         description_bytes: int, copies: int = 2) -> int:
    """A lower bound of the disk a build needs at its peak, ``copies`` times the output (comment above)."""
    pixels = sum(h * w for h, w in image_hw.values()) + STREAMS_PER_CAMERA * len(image_hw) * stream_hw[0] * stream_hw[1]
    return int(copies * (total_frames * pixels * BYTES_PER_PIXEL + description_bytes))


def free_bytes(path: Path) -> int:
    """Free bytes for an unprivileged writer on the file system that holds ``path`` (or
    would: its nearest existing ancestor)."""
    path = Path(path)
    while not path.exists() and path != path.parent:
        path = path.parent
    return shutil.disk_usage(path).free


def warn_if_short_of_space(root: Path, need: int) -> bool:
    """Print a warning and return True when less than ``need`` bytes are free at ``root``."""
    free = free_bytes(root)
    if free >= need:
        return False
    print(f"warning: {root} has {free / 1e6:.1f} MB free, the build needs at least about {need / 1e6:.1f} MB; "
          "it will likely stop with 'No space left on device' (exit 3). Finished episodes are kept in staging, "
          "so a rerun after freeing space resumes", file=sys.stderr)
    return True
