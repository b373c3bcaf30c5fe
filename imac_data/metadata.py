"""The one reader of a built dataset's metadata: ``meta/info.json`` and its ``imac`` block.

Every function that takes a dataset's metadata (here, :func:`imac_data.core.depth.depth_codec_of`,
:meth:`imac_data.core.rig.Rig.from_info`, :class:`imac_data.recipes.AugmentSettings.from_info`,
``imac_model.data.meta``) accepts what both LeRobot lines give, and reads the block through here:

* ``ds.meta`` (a ``LeRobotDatasetMetadata``) or ``ds`` itself: the file under its ``root`` is read,
  since LeRobot 0.6's ``ds.meta.info`` is a ``DatasetInfo`` that drops the ``imac`` block;
* the dataset's root (``str`` or ``Path``);
* the dict loaded from its ``meta/info.json``.

A LeRobot 0.6 ``DatasetInfo`` alone is refused with what to pass instead (docs/dataset-format.md)."""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from imac_data.errors import InputError
from imac_data.layout import ACTION, INFO, MOTION, R2S, S2G, depth_key, image_key, info_path

__all__ = ["SCHEMA_VERSION", "SUPPORTED_VERSIONS", "ADDED_IN", "RIG_KEYS", "STREAM_KEYS", "dataset_root", "dataset_info", "imac_block",
           "unchecked_imac_block", "chunk_timestamps"]

SCHEMA_VERSION = 2
SUPPORTED_VERSIONS = (1, 2)
ADDED_IN = {"workspace": 2}  # keys newer than version 1: required from that version on
RIG_KEYS = ("robot", "cameras", "controller", "gripper_surface", "workspace")  # the rig's part (Rig.to_info)
STREAM_KEYS = ("augment", "motion", "depth", "contact")  # the streams' settings, written when they are built
_PASS_INSTEAD = "pass ds.meta or the dataset's root instead"


def dataset_root(meta) -> Path | None:
    """The dataset directory of ``meta`` (None for a dict loaded from ``meta/info.json``)."""
    if isinstance(meta, (str, Path)):
        return Path(meta)
    if isinstance(meta, Mapping):
        return None
    root = getattr(meta, "root", None)
    if root is None:
        kind = type(meta).__name__
        hint = (" (LeRobot 0.6's ds.meta.info, which drops the imac block of meta/info.json)"
                if kind == "DatasetInfo" else "")
        raise InputError(f"dataset metadata: got a {kind}{hint}; {_PASS_INSTEAD} (or the dict loaded from "
                         f"{INFO})")
    return Path(root)


def dataset_info(meta) -> dict:
    """``meta/info.json`` as a dict, the ``imac`` block included (a dict given is returned as is)."""
    if isinstance(meta, Mapping):
        return meta if isinstance(meta, dict) else dict(meta)
    root = dataset_root(meta)
    path = info_path(root)
    try:
        info = json.loads(path.read_text())
    except (FileNotFoundError, NotADirectoryError):
        raise InputError(f"{root} is not a LeRobot dataset: {path} is missing") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise InputError(f"{path}: not valid JSON ({e})") from None
    if not isinstance(info, dict):
        raise InputError(f"{path}: expected a JSON object, got {type(info).__name__}")
    return info


def _where(meta) -> str:
    root = None if isinstance(meta, Mapping) else dataset_root(meta)
    return str(info_path(root)) if root is not None else INFO


def imac_block(meta, *, require: Sequence[str] = (), where: str | None = None) -> dict:
    """The ``imac`` block of a dataset's ``meta/info.json``, checked: present, a schema version
    this code reads, and the ``require``d keys there (a key newer than the dataset's version is
    not required). ``where`` names the file in messages."""
    info = dataset_info(meta)
    where = where or _where(meta)
    block = info.get("imac")
    if not isinstance(block, Mapping):
        hint = (f"; a dict without it is not the file's content (LeRobot 0.6's ds.meta.info drops it): {_PASS_INSTEAD}"
                if isinstance(meta, Mapping) else "")
        raise InputError(f"{where}: no 'imac' block (not built by imac, or rewritten by a tool that dropped it){hint}")
    version = block.get("schema_version")
    if version not in SUPPORTED_VERSIONS:
        raise InputError(f"{where}: imac.schema_version {version!r} is not one this code reads "
                         f"({list(SUPPORTED_VERSIONS)})")
    missing = [k for k in require if k not in block and ADDED_IN.get(k, 1) <= version]
    if missing:
        raise InputError(f"{where}: imac block lacks {missing}")
    return dict(block)


def unchecked_imac_block(meta) -> dict:
    """The ``imac`` block as it stands, unchecked; ``{}`` where there is none (a base dataset
    not built by imac, or one whose streams are being added)."""
    return dataset_info(meta).get("imac", {})


def chunk_timestamps(meta, cameras: Sequence[str] | None = None) -> dict[str, list[float]]:
    """``delta_timestamps`` for ``LeRobotDataset`` that load one contact chunk per item: the
    reference frame and the H future frames of RGB and depth, the H future frames of every
    control stream, and the actions ``a_t .. a_{t+H-1}`` (``meta``: ``ds.meta``, the dataset's
    root or its ``meta/info.json`` dict; ``cameras``: default all)."""
    info = dataset_info(meta)
    block = imac_block(info, require=("contact", "cameras"), where=_where(meta))
    if not block["contact"]:
        raise InputError(f"{_where(meta)}: imac.contact is empty: the dataset has no contact streams")
    fps = float(_field(info, "fps", meta))
    H = int(block["contact"]["chunk_size"])
    cameras = list(cameras) if cameras is not None else list(block["cameras"])
    future = [k / fps for k in range(1, H + 1)]
    out: dict[str, list[float]] = {}
    for cam in cameras:
        out[image_key(cam)] = [0.0, *future]
        out[depth_key(cam)] = [0.0, *future]
        for stream in (MOTION, R2S, S2G):
            out[f"{stream}.{cam}"] = list(future)
    out[ACTION] = [k / fps for k in range(H)]
    features = _field(info, "features", meta)
    return {k: v for k, v in out.items() if k in features}


def _field(info: Mapping, key: str, meta) -> Any:
    if key not in info:
        raise InputError(f"{_where(meta)}: no {key!r}")
    return info[key]
