"""Atomic file writes for dataset edits.

A dataset edit never leaves a half-written file behind: each file is written to a
temporary sibling (same directory, so the final ``os.replace`` is a rename on one file
system) and renamed over its destination when complete. Several edits that must land
together go into a :func:`staged_dataset` copy that is swapped into place at the end.
"""

from __future__ import annotations

import json
import os
import shutil
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

__all__ = ["atomic_path", "atomic_write_text", "atomic_write_json", "write_parquet_atomic", "replace_files",
           "staged_dataset"]


@contextmanager
def atomic_path(path: str | Path):
    """Yield a temporary sibling of ``path`` to write; it replaces ``path`` when the block
    ends without error and is removed otherwise."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{uuid.uuid4().hex[:8]}.tmp")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def atomic_write_text(path: str | Path, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def atomic_write_json(path: str | Path, data, indent: int = 4) -> None:
    """JSON as LeRobot writes its metadata (``indent=4``), atomically."""
    atomic_write_text(path, json.dumps(data, indent=indent))


def write_parquet_atomic(table, path: str | Path) -> None:
    import pyarrow.parquet as pq

    with atomic_path(path) as tmp:
        pq.write_table(table, tmp)


def replace_files(pairs: list[tuple[Path, Path]], backup_dir: Path) -> None:
    """Move each complete new file over its destination, in order (put ``meta/info.json``
    last); if any move fails, every destination already replaced gets its old content back
    (copies kept in ``backup_dir``) and new destinations are removed."""
    backup_dir.mkdir(parents=True, exist_ok=True)
    done: list[tuple[Path | None, Path]] = []
    try:
        for i, (new, dst) in enumerate(pairs):
            bak = None
            if dst.exists():
                bak = backup_dir / f"{i}-{dst.name}"
                shutil.copy2(dst, bak)
            os.replace(new, dst)
            done.append((bak, dst))
    except BaseException:
        for bak, dst in reversed(done):
            try:
                if bak is None:
                    dst.unlink()
                else:
                    os.replace(bak, dst)
            except OSError:
                pass
        raise


# ------------------------------------------------------------------------------ staging
def _link_or_copy(src: str, dst: str) -> None:
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)


@contextmanager
def staged_dataset(root: str | Path) -> Iterator[Path]:
    """A private copy of the dataset at ``root`` to write into; swapped into place
    when the ``with`` block ends without error, deleted otherwise::

        with staged_dataset(root) as work:
            add_video_streams(work, ...)
            add_video_streams(work, ...)

    The copy sits next to ``root`` (``.<name>.imac-staging``). Files under
    ``videos/`` are hard links to the originals (no copy of the big files), so code
    working in the copy must never modify an existing video file in place (this
    module only creates new ones); everything else is copied. The swap is two
    renames (``root`` -> ``.<name>.imac-old``, copy -> ``root``; :func:`imac_data.safety.swap_into_place`),
    then the old tree is deleted.
    """
    from imac_data.dataset.info import read_info
    from imac_data.safety import SIBLING_MARKER, make_sibling_dir, output_sibling, remove_sibling, swap_into_place

    root = Path(os.path.abspath(root))
    read_info(root)
    stage, old = output_sibling(root, "imac-staging"), output_sibling(root, "imac-old")
    for leftover in (stage, old):
        remove_sibling(leftover)
    make_sibling_dir(stage)
    try:
        for entry in root.iterdir():
            dst = stage / entry.name
            if entry.is_dir():
                shutil.copytree(entry, dst, copy_function=_link_or_copy if entry.name == "videos" else shutil.copy2)
            else:
                shutil.copy2(entry, dst)
        yield stage
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        raise
    (stage / SIBLING_MARKER).unlink()  # the copy becomes the dataset
    try:
        swap_into_place(stage, root, old_suffix="imac-old")
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        raise
