"""What protects the user's data: the inputs a command reads are never written or deleted,
and an output is replaced only when it is a dataset.

A build writes its output, a staging directory and a ``.old`` directory next to the
output (``--overwrite`` removes the previous output once the new one is complete);
``augment`` swaps a staged copy of the dataset into place. If any of those paths is,
contains or lies inside an input (the raw episodes, the calibration, the robot
description, the recipe), that input could be overwritten or deleted. Such a request
is refused before any work starts, with an :class:`InputError` naming both paths.

:func:`check_output` refuses, before any work, an output that ``--overwrite`` must not
replace (a file, a directory that is not a LeRobot dataset) and one that cannot be made
(a parent that is a file, a read-only or unwritable place: an
:class:`~imac_data.errors.EnvironmentFault`).
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path

from imac_data.errors import EnvironmentFault, InputError


def _real(path: Path) -> Path:
    # resolve() follows symlinks, so a link to the source counts as the source
    return Path(path).expanduser().resolve()


def _is_within(inner: Path, outer: Path) -> bool:
    return inner == outer or outer in inner.parents


SIBLING_SUFFIXES = ("staging", "old", "lock", "imac-staging", "imac-old")


def output_sibling(root: Path, suffix: str) -> Path:
    """``.<name>.<suffix>`` next to the output ``root`` (one of :data:`SIBLING_SUFFIXES`):
    where it is staged, locked or kept while it is replaced. ``root`` is made absolute first:
    ``.`` or ``x/..`` have no name of their own. abspath, not resolve: a symlinked root stays
    a symlink for the overlap checks."""
    if suffix not in SIBLING_SUFFIXES:
        raise ValueError(f"unknown output sibling {suffix!r}")
    root = Path(os.path.abspath(root))
    return root.parent / f".{root.name}.{suffix}"


# Written into the staging directories we make (removed before a staged copy becomes the output),
# so that a leftover one is known to be ours.
SIBLING_MARKER = ".imac-sibling"
_OWNED_BY = (SIBLING_MARKER, "BUILD_KEY", "meta/info.json")  # BUILD_KEY: build staging of earlier versions


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
    import shutil

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
    import shutil

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
        if any(root.iterdir()) and not (root / "meta" / "info.json").is_file():
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
