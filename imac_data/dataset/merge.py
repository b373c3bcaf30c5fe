"""Merge built datasets of one rig into one dataset, keeping the ``imac`` block.

LeRobot's ``aggregate_datasets`` does the merge (data, videos, episodes, stats). Around it:

* the inputs must come from the same rig and settings: their ``imac`` blocks must be equal
  (except ``build``), otherwise the merged dataset would claim one robot, calibration and
  codec for streams made with another;
* LeRobot 0.4.4's ``aggregate_stats`` orders ``stats.json`` by per-process string hashing:
  it is rewritten in feature order (:func:`~imac_data.dataset.info.order_stats`), so equal
  inputs give byte-identical outputs;
* ``aggregate_datasets`` writes a new dataset without our ``meta/imac/``: the ``imac`` block
  (``meta/imac/info.json``) is put back, and the robot description (``meta/imac/robot/``) is
  copied over;
* LeRobot 0.6.1's ``aggregate_datasets`` adds the video-encoder keys a feature's ``info`` lacks
  (``video.crf``, ``video.preset``, ... as null, for our streams) in the order of a frozenset,
  which follows Python's per-process string hashing: they are put in sorted order after the
  first input's keys, so that a resumed build equals an uninterrupted one byte for byte.

LeRobot appends each input's videos to the output file by rewriting that whole file (a Python loop over its
packets), so merging N inputs into one file costs O(N^2) packets (1,300 one-episode shards: 235 MB of their 1.3 GB
of video in 11 minutes, slowing as the files grew; benchmarks/results/build_speed.md). :func:`merge_datasets`
therefore merges at most :data:`MERGE_FAN_IN` inputs at a time, then the merged groups, a tree of O(log N) levels
that rewrites each packet once a level. Up to ``MERGE_FAN_IN`` inputs it is one call, as before. The groups of a
level are independent: given a runner (the build passes its worker pool), a level of at least
:data:`PARALLEL_MIN_GROUPS` groups is merged by several processes, each group's bytes the same as when merged alone.

The merge is staged: it is written to a temporary sibling of ``out`` and renamed into place
when complete.
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Mapping, Sequence
from pathlib import Path

from imac_data import lerobot_compat as lr
from imac_data.core.robot.description import DESCRIPTION_DIR, check_description
from imac_data.dataset.info import imac_block, order_stats, read_info, update_imac_info, write_info
from imac_data.dataset.streams import video_info
from imac_data.errors import InputError
from imac_data.layout import is_added_stream
from imac_data.metadata import imac_block_path, unchecked_imac_block

__all__ = ["merge_datasets", "aggregate_group", "check_same_rig", "order_feature_info", "restore_imac_block",
           "MERGE_FAN_IN", "PARALLEL_MIN_GROUPS"]

MERGE_FAN_IN = 8  # inputs a LeRobot aggregate takes at once (module docstring: its cost is quadratic in them)
# A level is spread over worker processes from this many groups on: a spawned worker's imports cost about 7
# CPU-seconds, a group of eight one-episode shards 2-10.
PARALLEL_MIN_GROUPS = 8


def check_same_rig(roots: Sequence[Path]) -> dict:
    """The common ``imac`` block of ``roots`` (``build`` excluded); :class:`InputError`
    naming the first dataset and key that differ."""
    blocks = []
    for root in roots:
        block = imac_block(read_info(root), str(imac_block_path(root)))
        block.pop("build", None)
        blocks.append(block)
    first = blocks[0]
    for root, block in zip(roots[1:], blocks[1:]):
        for key in sorted(set(first) | set(block)):
            if json.dumps(first.get(key), sort_keys=True) != json.dumps(block.get(key), sort_keys=True):
                raise InputError(f"cannot merge {root} with {roots[0]}: their imac.{key} differ (datasets of "
                                 "different rigs or settings)")
    return first


def order_feature_info(root: Path, first: Mapping) -> None:
    """Each feature's ``info`` in ``root``'s ``meta/info.json`` with its keys in the order of
    ``first`` (the first input's info.json), keys the merge added after them, sorted."""
    info = read_info(root)
    for key, feature in info["features"].items():
        given = (first["features"].get(key) or {}).get("info")
        if isinstance(feature.get("info"), dict) and isinstance(given, dict):
            keys = [k for k in given if k in feature["info"]] + sorted(k for k in feature["info"] if k not in given)
            feature["info"] = {k: feature["info"][k] for k in keys}
    write_info(root, info)


def aggregate_group(task: tuple[list[Path], Path, str, Path]) -> None:
    """LeRobot's aggregate of one group: ``(inputs in order, output, repo_id, Arrow cache folder)`` (a module-level
    function, so that a worker process can run it)."""
    group, dest, repo_id, cache = task
    with lr.arrow_cache_in(cache):
        lr.aggregate_datasets([repo_id] * len(group), repo_id, roots=group, aggr_root=dest)


def _aggregate_tree(roots: list[Path], out: Path, repo_id: str, fan_in: int, run_groups=None) -> None:
    """LeRobot's aggregate of ``roots`` (in order) into ``out``, ``fan_in`` inputs at a time: groups are merged
    into ``<out>.levels/<level>/<group>``, each level removed once the next is made. ``run_groups(fn, tasks)``
    runs a level's tasks (:func:`aggregate_group`) when it has enough of them; None: one after the other.
    LeRobot's Arrow copies of the inputs' parquet files go to ``<out>.levels/arrow`` and leave with it."""
    levels = out.with_name(out.name + ".levels")
    shutil.rmtree(levels, ignore_errors=True)  # what a killed merge left
    cache = levels / "arrow"
    level, inputs = 0, roots
    try:
        while len(inputs) > fan_in:
            level += 1
            groups = [inputs[i:i + fan_in] for i in range(0, len(inputs), fan_in)]
            merged = [levels / str(level) / f"{i:06d}" for i in range(len(groups))]
            tasks = [(group, dest, repo_id, cache) for group, dest in zip(groups, merged)]
            if run_groups is not None and len(tasks) >= PARALLEL_MIN_GROUPS:
                run_groups(aggregate_group, tasks)
            else:
                for task in tasks:
                    aggregate_group(task)
            if level > 1:
                shutil.rmtree(levels / str(level - 1))
            inputs = merged
        aggregate_group((inputs, out, repo_id, cache))
    finally:
        shutil.rmtree(levels, ignore_errors=True)


def merge_datasets(roots: Sequence[str | Path], out: str | Path, repo_id: str, *,
                   imac_extra: Mapping | None = None, description_dir: str | Path | None = None,
                   fan_in: int = MERGE_FAN_IN, run_groups=None) -> Path:
    """Merge the datasets ``roots`` (in order) into a new dataset at ``out`` (must not
    exist). ``imac_extra`` is merged into the restored ``imac`` block; the robot
    description is copied from ``description_dir`` (default: the first input's); ``fan_in``:
    inputs merged at a time; ``run_groups(fn, tasks)``: runs a tree level's merges, for example on
    worker processes (module docstring)."""
    roots = [Path(r) for r in roots]
    out = Path(out)
    if not roots:
        raise InputError("merge_datasets: no datasets given")
    if out.exists():
        raise InputError(f"merge_datasets: output {out} exists")
    if isinstance(fan_in, bool) or not isinstance(fan_in, int) or fan_in < 2:
        raise InputError(f"merge_datasets: fan_in must be an integer >= 2, got {fan_in!r}")
    block = check_same_rig(roots)
    source = Path(description_dir) if description_dir is not None else roots[0] / DESCRIPTION_DIR
    if "robot" in block:
        check_description(source, block["robot"]["description"], where=f"robot description {source}")
    tmp = out.with_name(f".{out.name}.merging")
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        _aggregate_tree(roots, tmp, repo_id, fan_in, run_groups)
        order_stats(tmp)
        order_feature_info(tmp, read_info(roots[0]))
        update_imac_info(tmp, {**block, **dict(imac_extra or {})})
        if "robot" in block:
            shutil.copytree(source, tmp / DESCRIPTION_DIR)
        os.rename(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out


def restore_imac_block(root: str | Path, original: str | Path) -> dict:
    """Put back the ``imac`` block (``meta/imac/info.json``) and the robot description of a
    dataset that a tool which writes a new dataset left them out of (LeRobot's
    ``merge_datasets``, ``add_features``, ``remove_feature``: docs/lerobot.md), from
    ``original``, the imac-built dataset it was made from. Every added stream left in ``root`` must be the original's (same dtype, shape, names,
    and its files of the codec and pixel format imac wrote); returns the restored block."""
    root, original = Path(root), Path(original)
    info, source = read_info(root), read_info(original)
    if "imac" in info:
        raise InputError(f"{imac_block_path(root)} already has an imac block: nothing to restore")
    block = imac_block(source, str(imac_block_path(original)))
    for key, feature in info["features"].items():
        if not is_added_stream(key):
            continue
        given = source["features"].get(key)
        if given is None:
            raise InputError(f"cannot restore {root} from {original}: its stream {key} is not in {original}")
        for field in ("dtype", "shape", "names"):
            if json.dumps(feature.get(field)) != json.dumps(given.get(field)):
                raise InputError(f"cannot restore {root} from {original}: {key}.{field} differs "
                                 f"({feature.get(field)} against {given.get(field)})")
        # LeRobot 0.4.4's delete_episodes / split_dataset re-encode a stream with LeRobot's camera encoder
        # (lossy AV1) and keep the original info: the files themselves must still be what the block describes
        want = tuple((given.get("info") or {}).get(f"video.{k}") for k in ("codec", "pix_fmt"))
        for path in sorted((root / "videos" / key).rglob("*.mp4")) if feature.get("dtype") == "video" else []:
            got = video_info(path)
            if (got["video.codec"], got["video.pix_fmt"]) != want:
                raise InputError(f"cannot restore {root} from {original}: {path.relative_to(root)} is "
                                 f"{got['video.codec']} {got['video.pix_fmt']}, not the {want[0]} {want[1]} imac "
                                 "wrote (re-encoded by the tool): rebuild the dataset instead")
    description = original / DESCRIPTION_DIR
    if "robot" in block:
        check_description(description, block["robot"]["description"], where=f"robot description {description}")
        if not (root / DESCRIPTION_DIR).exists():
            shutil.copytree(description, root / DESCRIPTION_DIR)
    block["build"] = {**block.get("build", {}), "imac_block_restored_from": str(original.resolve())}
    return unchecked_imac_block(update_imac_info(root, block))
