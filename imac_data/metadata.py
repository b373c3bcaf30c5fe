"""The one reader of a built dataset's metadata: ``meta/info.json`` and the ``imac`` block.

The block lives in a file of its own, ``meta/imac/info.json`` (schema version 3 on), beside the
robot description under ``meta/imac/robot/``, so that LeRobot, which warns about keys of
``meta/info.json`` it does not know, loads a dataset without a word. Datasets of versions 1 and
2 hold it under the ``imac`` key of ``meta/info.json``, and still read. In memory nothing
differs: :func:`dataset_info` gives ``meta/info.json``'s dict with the block under ``"imac"``.

Every function that takes a dataset's metadata (here, :func:`imac_data.core.depth.depth_codec_of`,
:meth:`imac_data.core.rig.Rig.from_info`, :class:`imac_data.recipes.AugmentSettings.from_info`,
``imac_model.data.meta``) accepts what both LeRobot lines give, and reads the block through here:

* ``ds.meta`` (a ``LeRobotDatasetMetadata``) or ``ds`` itself: the files under its ``root`` are read,
  since ``ds.meta.info`` has no block (LeRobot 0.6's is a ``DatasetInfo``, which drops unknown keys);
* the dataset's root (``str`` or ``Path``);
* the dict :func:`dataset_info` gives (``meta/info.json`` with the block).

A LeRobot 0.6 ``DatasetInfo`` alone is refused with what to pass instead (docs/dataset-format.md)."""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from imac_data.errors import InputError
from imac_data.layout import ACTION, IMAC_INFO, INFO, MOTION, R2S, S2G, depth_key, imac_info_path, image_key, info_path

__all__ = ["SCHEMA_VERSION", "SUPPORTED_VERSIONS", "ADDED_IN", "RIG_KEYS", "STREAM_KEYS", "dataset_root", "dataset_info", "imac_block",
           "unchecked_imac_block", "imac_block_path", "chunk_timestamps"]

SCHEMA_VERSION = 3  # 3: the block moved from meta/info.json's "imac" key to meta/imac/info.json, its keys unchanged
SUPPORTED_VERSIONS = (1, 2, 3)
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
        hint = (" (LeRobot 0.6's ds.meta.info, which has no imac block)"
                if kind == "DatasetInfo" else "")
        raise InputError(f"dataset metadata: got a {kind}{hint}; {_PASS_INSTEAD} (or the dict "
                         "imac_data.metadata.dataset_info gives)")
    return Path(root)


def dataset_info(meta) -> dict:
    """``meta/info.json`` as a dict, with the ``imac`` block under ``"imac"``: the content of
    ``meta/imac/info.json`` where that file is (schema version 3 on), else whatever
    ``meta/info.json`` holds there (versions 1 and 2). A dict given is returned as is."""
    if isinstance(meta, Mapping):
        return meta if isinstance(meta, dict) else dict(meta)
    root = dataset_root(meta)
    try:
        info = _json_object(info_path(root))
    except (FileNotFoundError, NotADirectoryError):
        raise InputError(f"{root} is not a LeRobot dataset: {info_path(root)} is missing") from None
    block = imac_info_path(root)
    if block.is_file():
        info["imac"] = _json_object(block)
    return info


def _json_object(path: Path) -> dict:
    try:
        data = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise InputError(f"{path}: not valid JSON ({e})") from None
    if not isinstance(data, dict):
        raise InputError(f"{path}: expected a JSON object, got {type(data).__name__}")
    return data


def imac_block_path(root: str | Path) -> Path:
    """The file that holds the ``imac`` block of the dataset at ``root``: ``meta/imac/info.json``,
    or ``meta/info.json`` for a dataset of version 1 or 2 (or one without a block)."""
    path = imac_info_path(root)
    return path if path.is_file() else info_path(root)


def _where(meta) -> str:
    root = None if isinstance(meta, Mapping) else dataset_root(meta)
    return str(imac_block_path(root)) if root is not None else INFO


def imac_block(meta, *, require: Sequence[str] = (), where: str | None = None) -> dict:
    """The ``imac`` block of a dataset (:func:`dataset_info`), checked: present, a schema version
    this code reads, and the ``require``d keys there (a key newer than the dataset's version is
    not required). ``where`` names the file in messages."""
    info = dataset_info(meta)
    where = where or _where(meta)
    block = info.get("imac")
    if not isinstance(block, Mapping):
        hint = (f"; a dict without it is not what imac_data.metadata.dataset_info gives (meta/info.json alone and "
                f"ds.meta.info have no block): {_PASS_INSTEAD}" if isinstance(meta, Mapping) else
                f", and no {IMAC_INFO}")
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
    root or its :func:`dataset_info` dict; ``cameras``: default all)."""
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
