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


def check_output(root: Path, *, overwrite: bool, what: str = "--root") -> None:
    """Refuse an output that may not be replaced, or cannot be made, before any work starts.

    An existing ``root`` is replaced only with ``overwrite``, and only when it is a LeRobot
    dataset (``meta/info.json``) or an empty directory: never a file nor someone's other
    directory (:class:`InputError`). The nearest existing ancestor must be a directory this
    process may write (else :class:`~imac_data.errors.EnvironmentFault`).
    """
    root = Path(root)
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
