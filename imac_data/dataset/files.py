"""Atomic file writes for dataset edits, and the copy of a dataset that an edit works on.

A dataset edit never leaves a half-written file behind: each file is written to a temporary
sibling (same directory, so the final ``os.replace`` is a rename on one file system) and
renamed over its destination when complete. Edits that must land together work on a
:func:`copy_for_edit` that the build's staged flow swaps into place.
"""

from __future__ import annotations

import json
import os
import shutil
import uuid
from contextlib import contextmanager
from pathlib import Path

import pyarrow.parquet as pq

from imac_data.layout import STATS_COLUMNS, VIDEO_COLUMNS, VIDEOS_DIR, episodes_dir, image_key, info_path, stats_path

__all__ = ["atomic_path", "atomic_write_text", "atomic_write_json", "write_parquet_atomic", "replace_files",
           "copy_for_edit", "copy_source"]


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
            else:
                dst.parent.mkdir(parents=True, exist_ok=True)  # e.g. meta/imac/ of a dataset without a block yet
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


# ------------------------------------------------------------------------------ copies
def _link_or_copy(src: str, dst: str) -> None:
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)


def copy_for_edit(root: str | Path, dst: str | Path) -> Path:
    """A copy of the dataset at ``root`` at ``dst`` to edit and swap in. Files under
    ``videos/`` are hard links to the originals (no copy of the big files), so an edit must
    never modify an existing video file in place (ours only add files); the rest is copied."""
    root, dst = Path(root), Path(dst)
    dst.mkdir()
    for entry in root.iterdir():
        if entry.is_dir():
            shutil.copytree(entry, dst / entry.name,
                            copy_function=_link_or_copy if entry.name == VIDEOS_DIR else shutil.copy2)
        else:
            shutil.copy2(entry, dst / entry.name)
    return dst




def copy_source(src, dst: Path, cameras: dict[str, str]) -> None:
    """A byte-identical copy of ``src`` at ``dst`` with its camera features renamed to
    ``observation.images.<cam>`` (``cameras``: source key -> camera) and unmapped camera
    features dropped. The video files are copied unchanged, only their directories move."""
    shutil.copytree(src.root, dst, ignore=shutil.ignore_patterns(".cache", ".imac-tmp-*"))
    rename = {k: image_key(c) for k, c in cameras.items()}
    drop = [k for k in src.video_keys if k not in rename]
    if all(k == v for k, v in rename.items()) and not drop:
        return
    aside = dst / ".imac-rekey"  # moved aside first, so that a rename onto another source key cannot clash
    aside.mkdir()
    for key in [*rename, *drop]:
        if (dst / VIDEOS_DIR / key).exists():
            (dst / VIDEOS_DIR / key).rename(aside / key)
    for key, new in rename.items():
        if (aside / key).exists():
            (aside / key).rename(dst / VIDEOS_DIR / new)
    shutil.rmtree(aside)  # what is left: the dropped cameras' copies

    def rekey(name: str) -> str | None:
        for prefix in (VIDEO_COLUMNS, STATS_COLUMNS):
            if name.startswith(prefix):
                rest = name[len(prefix):]
                for key in sorted([*rename, *drop], key=len, reverse=True):
                    if rest.startswith(key + "/"):
                        return None if key in drop else prefix + rename[key] + rest[len(key):]
        return name

    for f in sorted(episodes_dir(dst).rglob("*.parquet")):
        table = pq.read_table(f)
        keep = [(n, rekey(n)) for n in table.column_names]
        table = table.select([n for n, m in keep if m is not None]).rename_columns([m for _, m in keep if m])
        write_parquet_atomic(table, f)
    info = json.loads(info_path(dst).read_text())
    info["features"] = {rename.get(k, k): v for k, v in info["features"].items() if k not in drop}
    atomic_write_json(info_path(dst), info)
    stats_file = stats_path(dst)
    if stats_file.is_file():
        stats = json.loads(stats_file.read_text())
        atomic_write_json(stats_file, {rename.get(k, k): v for k, v in stats.items() if k not in drop})
