"""The writer of a dataset's metadata: ``meta/info.json`` and the ``imac`` block, everything needed
to decode a dataset's added streams and to rebuild them, versioned (schema in
``docs/dataset-format.md``).

In memory the block is ``info["imac"]`` (:func:`imac_data.metadata.dataset_info`); on disk it is a
file of its own, ``meta/imac/info.json``, and ``meta/info.json`` has no ``imac`` key, so that
LeRobot loads the dataset without warning about a key it does not know. Every write of the two
goes through here (:func:`write_info`, or :func:`stage_info` for a staged edit): a dataset of
version 1 or 2, with the block inside ``meta/info.json``, has it moved out on its next write.

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
from imac_data.layout import imac_info_path, info_path, stats_path
from imac_data.metadata import RIG_KEYS, SCHEMA_VERSION, STREAM_KEYS, SUPPORTED_VERSIONS, dataset_info
from imac_data.metadata import imac_block as _read_block

__all__ = ["SCHEMA_VERSION", "SUPPORTED_VERSIONS", "RIG_KEYS", "STREAM_KEYS", "read_info", "write_info",
           "split_info", "stage_info", "update_imac_info", "imac_block", "order_stats", "base_block"]


def read_info(root: str | Path) -> dict:
    """``meta/info.json`` of the dataset at ``root`` with its ``imac`` block
    (:func:`imac_data.metadata.dataset_info`)."""
    return dataset_info(Path(root))


def split_info(info: Mapping) -> tuple[dict, dict | None]:
    """An info dict as its two files hold it: ``meta/info.json`` (without the ``imac`` key)
    and ``meta/imac/info.json`` (the block; None where there is none)."""
    rest = {k: v for k, v in info.items() if k != "imac"}
    block = info.get("imac")
    return rest, (dict(block) if block is not None else None)


def write_info(root: str | Path, info: Mapping) -> None:
    """``info`` (a :func:`read_info` dict) as its two files, each atomically, in LeRobot's
    layout (``indent=4``): the block to ``meta/imac/info.json`` (removed where ``info`` has
    none), then ``meta/info.json`` without it."""
    rest, block = split_info(info)
    path = imac_info_path(root)
    if block is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_json(path, block)
    atomic_write_json(info_path(root), rest)
    if block is None:
        path.unlink(missing_ok=True)


def stage_info(root: str | Path, info: Mapping, tmp: Path) -> list[tuple[Path, Path]]:
    """:func:`write_info` for a staged edit: the two files written into ``tmp``, returned as
    ``(new file, destination)`` pairs to move into place in order (``meta/info.json`` last).
    ``info`` is a :func:`read_info` dict, so a dataset whose block is in its own file has
    it there."""
    rest, block = split_info(info)
    staged = []
    if block is not None:
        (tmp / "imac_info.json").write_text(json.dumps(block, indent=4))
        staged.append((tmp / "imac_info.json", imac_info_path(root)))
    (tmp / "info.json").write_text(json.dumps(rest, indent=4))
    staged.append((tmp / "info.json", info_path(root)))
    return staged


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
