"""The ``imac`` block of ``meta/info.json``: everything needed to decode a dataset's added streams
and to rebuild them, under one versioned key (schema in ``docs/dataset-format.md``).

The rig keys (``robot``, ``cameras``, ``controller``, ``gripper_surface``, ``workspace``) with
the description under ``meta/imac/robot/`` rebuild the rig (:meth:`imac_data.core.rig.Rig.from_info`).
Version 2 added ``workspace``; version 1 datasets still read, without a crop. LeRobot's
``aggregate_datasets`` drops the block, so :func:`imac_data.dataset.merge.merge_datasets` puts it back."""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path

from imac_data import __version__
from imac_data.dataset.files import atomic_write_json
from imac_data.layout import info_path, stats_path
from imac_data.metadata import RIG_KEYS, SCHEMA_VERSION, STREAM_KEYS, SUPPORTED_VERSIONS, dataset_info
from imac_data.metadata import imac_block as _read_block

__all__ = ["SCHEMA_VERSION", "SUPPORTED_VERSIONS", "RIG_KEYS", "STREAM_KEYS", "read_info", "write_info",
           "update_imac_info", "imac_block", "order_stats", "base_block"]


def read_info(root: str | Path) -> dict:
    """``meta/info.json`` of the dataset at ``root`` (:func:`imac_data.metadata.dataset_info`)."""
    return dataset_info(Path(root))


def write_info(root: str | Path, info: Mapping) -> None:
    """``meta/info.json``, atomically, in LeRobot's layout (``indent=4``)."""
    atomic_write_json(info_path(root), info)


def update_imac_info(root: str | Path, block: Mapping) -> dict:
    """Merge ``block`` into ``info["imac"]`` (setting ``schema_version``); returns the new info."""
    info = read_info(root)
    imac = {**info.get("imac", {}), **json.loads(json.dumps(block))}
    imac.pop("schema_version", None)
    info["imac"] = {"schema_version": SCHEMA_VERSION, **imac}
    write_info(root, info)
    return info


def base_block(rig) -> dict:
    """The block of a base dataset: schema, builder version, the rig, the pose convention."""
    return {"schema_version": SCHEMA_VERSION, "builder_version": __version__, **rig.to_info(),
            "camera_pose_convention": "camera-to-world, OpenCV axes, row-major 4x4"}


def imac_block(info: Mapping, where: str = "meta/info.json", *, require: tuple[str, ...] = RIG_KEYS) -> dict:
    """The ``imac`` block of ``info``, checked (:func:`imac_data.metadata.imac_block`; by
    default the rig keys are required)."""
    return _read_block(info, require=require, where=where)


def order_stats(root: str | Path) -> None:
    """``meta/stats.json`` with its keys in feature order. LeRobot's ``aggregate_stats``
    collects feature names in a set, so its key order follows Python's per-process string
    hashing; equal builds must be byte-identical."""
    root = Path(root)
    info = read_info(root)
    path = stats_path(root)
    stats = json.loads(path.read_text())
    order = [k for k in info["features"] if k in stats] + sorted(k for k in stats if k not in info["features"])
    atomic_write_json(path, {k: stats[k] for k in order})
