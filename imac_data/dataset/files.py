"""Atomic file writes for dataset edits.

A dataset edit never leaves a half-written file behind: each file is written to a
temporary sibling (same directory, so the final ``os.replace`` is a rename on one file
system) and renamed over its destination when complete.
"""

from __future__ import annotations

import json
import os
import uuid
from contextlib import contextmanager
from pathlib import Path

__all__ = ["atomic_path", "atomic_write_text", "atomic_write_json", "write_parquet_atomic"]


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
