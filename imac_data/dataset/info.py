"""The ``imac`` block of ``meta/info.json``: everything needed to decode a dataset's added
streams and to rebuild them, under one versioned key.

Schema version 2 (``imac.schema_version``)::

    imac:
      schema_version: 2
      builder_version: "0.1.0"                    # imac_data.__version__
      robot:       {name, joint_map, gripper_links, state_names,
                    description: {path, urdf_sha256, files: {meshes/...: sha256}, bytes}}
      cameras:     {cam: {K, width, height, T_world_cam | link + T_link_cam}}   # at the image size
      controller:  {mode, grippers, absolute_indices, delta_grippers, clip_low, clip_high}
      gripper_surface: {links, spacing, seed}
      workspace:   {min: [x, y, z], max: [x, y, z], depth_range: [near, far], source} | null
                                                  # the contact streams' scene crop (imac_data.core.contact.workspace);
                                                  # far null = no far limit; null = not cropped
      camera_pose_convention: "camera-to-world, OpenCV axes, row-major 4x4"
      augment:     AugmentSettings (resolution, motion source, codec, chunk, caps, ...)
      motion:      {source, frame_rule}
      depth:       {codec, encoding, encoder_versions, source, streams: {cam: {key, height, width, K}}, decode}
      contact:     {chunk_size, reference_rule, cap, scene_crop, cap_column, colormap, tolerance}
      build:       {recipe, command, episodes}      # built datasets only

``robot`` + ``cameras`` + ``controller`` + ``gripper_surface`` + ``workspace`` are the rig
(:meth:`imac_data.core.rig.Rig.to_info`); with the description under ``meta/imac/robot/``
they rebuild it (:meth:`imac_data.core.rig.Rig.from_info`). A base dataset (ingest only) has
the rig keys; an augmented one all but ``build``.

Versions: 2 added ``workspace`` (and ``contact.scene_crop``). Version 1 datasets still
read: they have no workspace, and their contact streams were built without a crop, so
:meth:`~imac_data.core.rig.Rig.from_info` gives a rig without one and an online rebuild
matches them. Code that only knows version 1 refuses version 2 rather than rebuilding
contact images without the crop.

LeRobot 0.4.4's ``aggregate_datasets`` drops this block (it rebuilds ``info.json``);
:func:`imac_data.dataset.merge.merge_datasets` puts it back.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path

from imac_data import __version__
from imac_data.dataset.files import atomic_write_json
from imac_data.errors import InputError
from imac_data.layout import info_path, stats_path

__all__ = ["SCHEMA_VERSION", "SUPPORTED_VERSIONS", "RIG_KEYS", "STREAM_KEYS", "read_info", "write_info",
           "update_imac_info", "imac_block", "order_stats", "base_block"]

SCHEMA_VERSION = 2
SUPPORTED_VERSIONS = (1, 2)
RIG_KEYS = ("robot", "cameras", "controller", "gripper_surface", "workspace")
STREAM_KEYS = ("augment", "motion", "depth", "contact")
ADDED_IN = {"workspace": 2}  # keys newer than version 1: required from that version on


def read_info(root: str | Path) -> dict:
    path = info_path(root)
    if not path.is_file():
        raise InputError(f"{root} is not a LeRobot dataset: {path} is missing")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise InputError(f"{path}: not valid JSON ({e})") from None


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
    """The ``imac`` block of ``info``, checked: present, a known schema version, and the
    ``require``d keys there. :class:`InputError` otherwise."""
    block = info.get("imac") if isinstance(info, Mapping) else None
    if not isinstance(block, Mapping):
        raise InputError(f"{where}: no 'imac' block (not built by imac, or merged by a tool that dropped it)")
    version = block.get("schema_version")
    if version not in SUPPORTED_VERSIONS:
        raise InputError(f"{where}: imac.schema_version {version!r} is not one this code reads "
                         f"({list(SUPPORTED_VERSIONS)})")
    missing = [k for k in require if k not in block and ADDED_IN.get(k, 1) <= version]
    if missing:
        raise InputError(f"{where}: imac block lacks {missing}")
    return dict(block)


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
