"""Per-frame and per-episode columns of a LeRobot v3.0 dataset.

* :func:`add_frame_column`: a float32 feature in the data parquet files (e.g. the contact
  caps of each frame's chunk), with its feature entry in ``info.json`` and its stats per
  episode (``meta/episodes``, ``stats/<key>/*``) and overall (``stats.json``), computed
  with LeRobot's own ``get_feature_stats`` / ``aggregate_stats``;
* :func:`add_episode_columns`: plain per-episode metadata columns in ``meta/episodes``
  (e.g. ``imac/source``, ``imac/success``).

Both are staged: every new file is written next to the dataset's and moved into place at
the end (``info.json`` last); a failure leaves the dataset as it was.
"""

from __future__ import annotations

import json
import shutil
import uuid
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from imac_data import lerobot_compat as lr
from imac_data.dataset.files import replace_files
from imac_data.dataset.info import read_info, stage_info
from imac_data.errors import InputError
from imac_data.layout import episodes_dir, stats_column, stats_path

__all__ = ["add_frame_column", "add_episode_columns"]


def _staging(root: Path) -> Path:
    tmp = root / f".imac-tmp-{uuid.uuid4().hex[:12]}"
    tmp.mkdir()
    return tmp


def add_frame_column(root: Path, key: str, per_episode: list[np.ndarray], names: list[str]) -> None:
    """Add a float32 per-frame feature ``key`` (values ``(T_e, N)`` per episode, in episode
    order) to the data parquet files, ``info.json`` and the stats."""
    root = Path(root)
    info = read_info(root)
    if key in info["features"]:
        raise InputError(f"{root}: feature {key} already exists")
    values = {ep: np.asarray(v, dtype=np.float32).reshape(len(v), -1) for ep, v in enumerate(per_episode)}
    if len(values) != int(info["total_episodes"]):
        raise InputError(f"{root}: values for {len(values)} episodes, the dataset has {info['total_episodes']}")
    width = len(names)
    bad = [ep for ep, v in values.items() if v.shape[1] != width]
    if bad:
        raise InputError(f"{key}: episode {bad[0]} has {values[bad[0]].shape[1]} values per frame, expected {width}")
    lengths = np.array([len(values[ep]) for ep in range(len(values))])
    offsets = np.concatenate([[0], np.cumsum(lengths)[:-1]])
    flat = np.concatenate([values[ep] for ep in range(len(values))])
    tmp = _staging(root)
    try:
        staged: list[tuple[Path, Path]] = []
        for file in sorted((root / "data").rglob("*.parquet")):
            table = pq.read_table(file)
            eps = table.column("episode_index").to_numpy()
            frame = table.column("frame_index").to_numpy()
            if (frame >= lengths[eps]).any():
                raise InputError(f"{key}: fewer values than frames in {file}")
            column = flat[offsets[eps] + frame]
            arr = pa.array(list(column), type=pa.list_(pa.float32()))
            out = tmp / file.relative_to(root)
            out.parent.mkdir(parents=True, exist_ok=True)
            pq.write_table(table.append_column(key, arr), out)
            staged.append((out, file))
        # stats: per episode (meta/episodes columns) and global (meta/stats.json), as LeRobot computes them
        ep_stats = {ep: lr.get_feature_stats(v, axis=0, keepdims=v.ndim == 1) for ep, v in values.items()}
        for file in sorted(episodes_dir(root).rglob("*.parquet")):
            table = pq.read_table(file)
            idx = table.column("episode_index").to_pylist()
            for stat in ep_stats[idx[0]]:
                col = [np.asarray(ep_stats[i][stat]).reshape(-1).tolist() for i in idx]
                table = table.append_column(stats_column(key, stat), pa.array(col))
            out = tmp / file.relative_to(root)
            out.parent.mkdir(parents=True, exist_ok=True)
            pq.write_table(table, out)
            staged.append((out, file))
        stats_file = stats_path(root)
        stats = json.loads(stats_file.read_text()) if stats_file.is_file() else {}
        total = lr.aggregate_stats([{key: s} for s in ep_stats.values()])[key]
        stats[key] = {k: np.asarray(v).tolist() for k, v in total.items()}
        (tmp / "stats.json").write_text(json.dumps(stats, indent=4))
        staged.append((tmp / "stats.json", stats_file))
        info["features"][key] = {"dtype": "float32", "shape": [width], "names": names}
        staged += stage_info(root, info, tmp)  # the imac block to meta/imac/info.json, info.json last
        replace_files(staged, tmp / "backup")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def add_episode_columns(root: Path, rows: list[dict], columns: dict[str, pa.DataType]) -> None:
    """Per-episode columns in ``meta/episodes`` (replaced if present): ``rows[i][name]`` is
    episode ``i``'s value of column ``name``, whose arrow type is ``columns[name]``."""
    root = Path(root)
    tmp = _staging(root)
    try:
        staged = []
        for file in sorted(episodes_dir(root).rglob("*.parquet")):
            table = pq.read_table(file)
            index = table.column("episode_index").to_pylist()
            for name, typ in columns.items():
                values = [rows[i][name] for i in index]
                if name in table.column_names:
                    table = table.drop(name)
                table = table.append_column(name, pa.array(values, type=typ))
            out = tmp / file.relative_to(root)
            out.parent.mkdir(parents=True, exist_ok=True)
            pq.write_table(table, out)
            staged.append((out, file))
        replace_files(staged, tmp / "backup")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
