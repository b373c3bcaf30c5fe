"""Evaluation results as files: strict JSON (a non-finite number, such as the PSNR of identical
frames, is written as ``null`` and listed under ``"nonfinite"``), and per-episode outcomes of
policies in the world model and in reality, read from CSV or JSON."""

from __future__ import annotations

import csv
import json
import math
import os
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from imac_data.errors import InputError
from imac_model.evaluate.success import _FALSE, _TRUE

__all__ = ["json_ready", "write_json", "read_outcomes"]


def json_ready(tree, path: str = "", found: dict | None = None):
    """``tree`` with every non-finite float replaced by None (recorded in ``found`` as
    ``{dotted.path: "inf" | "-inf" | "nan"}``), numpy scalars as Python numbers, paths and
    tuples as strings and lists."""
    found = {} if found is None else found
    if isinstance(tree, Mapping):
        return {str(k): json_ready(v, f"{path}.{k}" if path else str(k), found) for k, v in tree.items()}
    if isinstance(tree, (list, tuple)):
        return [json_ready(v, f"{path}[{i}]", found) for i, v in enumerate(tree)]
    if isinstance(tree, (bool, np.bool_)):
        return bool(tree)
    if isinstance(tree, (int, np.integer)):
        return int(tree)
    if isinstance(tree, (float, np.floating)):
        x = float(tree)
        if math.isfinite(x):
            return x
        found[path] = "nan" if math.isnan(x) else ("inf" if x > 0 else "-inf")
        return None
    if isinstance(tree, Path):
        return str(tree)
    if isinstance(tree, np.ndarray):
        return json_ready(tree.tolist(), path, found)
    return tree


def write_json(path: str | Path, result: Mapping) -> Path:
    """Write ``result`` as strict JSON (see :func:`json_ready`), atomically."""
    found: dict = {}
    clean = json_ready(result, "", found)
    if found:
        clean["nonfinite"] = found
    text = json.dumps(clean, indent=2, allow_nan=False)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text + "\n")
    os.replace(tmp, path)
    return path


# --------------------------------------------------------------------------- shared pieces


_SOURCES = {"world_model": "world_model", "wm": "world_model", "world-model": "world_model", "real": "real"}


def read_outcomes(path: str | Path) -> tuple[dict, dict]:
    """Per-episode outcomes ``(world_model, real)``, each ``{policy or (policy, group): [0/1 ...]}``,
    from a CSV (columns ``policy``, ``source`` = world_model | real, ``success``; optional
    ``group``) or a JSON ``{"world_model": {policy: [..] or {group: [..]}}, "real": {...}}``."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: outcomes file not found")
    sides: dict[str, dict] = {"world_model": {}, "real": {}}
    if path.suffix.lower() == ".json":
        try:
            data = json.loads(path.read_text())
        except json.JSONDecodeError as e:
            raise InputError(f"{path}: not JSON ({e})") from None
        if not isinstance(data, dict) or set(data) != {"world_model", "real"}:
            raise InputError(f"{path}: expected an object with exactly the keys 'world_model' and 'real'")
        for side, policies in data.items():
            if not isinstance(policies, dict):
                raise InputError(f"{path}: {side!r} must map policies to outcome lists (or groups to lists)")
            for policy, v in policies.items():
                if isinstance(v, dict):
                    for group, outcomes in v.items():
                        sides[side][(policy, group)] = outcomes
                else:
                    sides[side][policy] = v
        return sides["world_model"], sides["real"]
    with path.open(newline="") as f:
        reader = csv.DictReader(f)
        columns = [c.strip() for c in (reader.fieldnames or [])]
        for col in ("policy", "source", "success"):
            if col not in columns:
                raise InputError(f"{path}: missing column {col!r} (columns: {columns}); expected "
                                 "policy,group,source,success with source world_model or real")
        grouped = "group" in columns
        for line, row in enumerate(reader, start=2):
            row = {k.strip(): (v or "").strip() for k, v in row.items() if k is not None}
            side = _SOURCES.get(row["source"].lower())
            if side is None:
                raise InputError(f"{path}:{line}: source {row['source']!r} is not world_model or real")
            value = row["success"].lower()
            if value in _TRUE | _FALSE:
                outcome = 1.0 if value in _TRUE else 0.0
            else:
                try:
                    outcome = float(value)
                except ValueError:
                    raise InputError(f"{path}:{line}: success {row['success']!r} is not 1/0, true/false or a "
                                     "score") from None
            key = (row["policy"], row["group"]) if grouped and row.get("group") else row["policy"]
            sides[side].setdefault(key, []).append(outcome)
    if not sides["world_model"] and not sides["real"]:
        raise InputError(f"{path}: no outcomes")
    return sides["world_model"], sides["real"]
