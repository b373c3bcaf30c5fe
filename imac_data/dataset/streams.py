"""Add video streams to an existing LeRobot v3.0 dataset, chunk by chunk.

LeRobot 0.4.4 adds parquet columns but no video stream, so this writes one by hand, laid out
exactly as LeRobot writes a camera (mp4 files under ``info["video_path"]``, the episode's
location and stats columns in ``meta/episodes``, the feature in ``info.json``, stats in
``stats.json``), so ``LeRobotDataset``, ``delta_timestamps`` and ``aggregate_datasets`` treat
it like any camera (``docs/dataset-format.md``, "How an added stream is stored"); a LeRobot 0.6
depth map (12-bit codes, :mod:`imac_data.core.depth_map`) is stored as LeRobot 0.6 writes one.
:class:`StreamWriter` takes frames as they are made (memory: the encoders' buffers). Existing
files are never opened for writing, and the metadata is replaced only once every episode is
encoded, ``meta/info.json`` last; on error the dataset is left as it was."""

from __future__ import annotations

import json
import os
import shutil
import uuid
from collections.abc import Callable, Iterable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import suppress
from pathlib import Path
from typing import Any

from imac_data import lerobot_compat as lr
from imac_data.core.depth_map import PIX_FMT as DEPTH_MAP_PIX_FMT
from imac_data.core.depth_map import DepthMapParams
from imac_data.dataset.info import read_info, stage_info
from imac_data.dataset.videos import (
    SUBSAMPLED_CHROMA,
    ImageStats,
    VideoEncoding,
    VideoWriter,
    code_batches,
    frame_batches,
)
from imac_data.errors import InputError
from imac_data.layout import (
    DEFAULT_VIDEO_PATH,
    STATS_COLUMNS,
    VIDEO_COLUMNS,
    VIDEOS_DIR,
    episodes_dir,
    stats_column,
    stats_path,
    video_column,
)

__all__ = ["StreamWriter", "add_video_streams", "add_video_stream", "video_info", "depth_map_video_info",
           "episode_lengths", "insert_columns_after", "STAT_KEYS"]

STAT_KEYS = ("min", "max", "mean", "std", "count", "q01", "q10", "q50", "q90", "q99")


# ----------------------------------------------------------------------------- dataset files


def read_v3_info(root: Path) -> dict:
    info = read_info(root)
    if info.get("codebase_version") != "v3.0":
        raise InputError(f"{root}: dataset format {info.get('codebase_version')!r}; only LeRobot v3.0 is supported")
    return info


def episode_files(root: Path) -> list[Path]:
    files = sorted(episodes_dir(root).glob("*/*.parquet"))
    if not files:
        raise InputError(f"{root}: no meta/episodes/*/*.parquet files")
    return files


def episode_lengths(root: Path) -> dict[int, int]:
    """``{episode_index: length}`` from ``meta/episodes``."""
    import pyarrow.parquet as pq

    lengths: dict[int, int] = {}
    for f in episode_files(root):
        t = pq.read_table(f, columns=["episode_index", "length"])
        lengths.update(zip(t.column("episode_index").to_pylist(), t.column("length").to_pylist()))
    return lengths


def video_info(path: Path) -> dict[str, Any]:
    """The keys LeRobot's ``get_video_info`` writes, read the same way. (Its own function
    cannot be used: it raises on planar RGB ``gbrp``, which libx264rgb writes.)"""
    import av

    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        return {
            "video.height": stream.height,
            "video.width": stream.width,
            "video.codec": stream.codec.canonical_name,
            "video.pix_fmt": stream.pix_fmt,
            "video.is_depth_map": False,
            "video.fps": int(stream.base_rate),
            "video.channels": 3,
            "has_audio": len(container.streams.audio) > 0,
        }


def depth_map_video_info(path: Path, encoding: VideoEncoding, params: DepthMapParams) -> dict[str, Any]:
    """A LeRobot depth map's ``info`` block, key for key as LeRobot 0.6.1 writes it
    (``get_video_info(path, DepthEncoderConfig)`` plus ``depth_unit``): the stream's own
    fields, the encoder's settings, the quantiser, the marker. Its stats are in metres."""
    import av

    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        info = {
            "video.height": stream.height,
            "video.width": stream.width,
            "video.codec": stream.codec.canonical_name,
            "video.pix_fmt": stream.pix_fmt,
            "video.fps": int(stream.base_rate),
            "video.channels": 1,
            "has_audio": len(container.streams.audio) > 0,
        }
    info.update({"video.g": encoding.gop, "video.crf": encoding.crf, "video.preset": encoding.preset,
                 "video.fast_decode": 0, "video.video_backend": "pyav", "video.extra_options": dict(encoding.options),
                 **params.info(), "is_depth_map": True, "depth_unit": "m"})
    return info


def insert_columns_after(table, after_prefix: str, fallback: str, columns: list[tuple[str, Any]]):
    """Insert columns after the last column starting with ``after_prefix`` (else after
    ``fallback``, else at the end), keeping LeRobot's column order."""
    names = table.column_names
    idx = [i for i, n in enumerate(names) if n.startswith(after_prefix)]
    pos = (idx[-1] + 1) if idx else (names.index(fallback) + 1 if fallback in names else len(names))
    for offset, (name, array) in enumerate(columns):
        table = table.add_column(pos + offset, name, array)
    return table


def _check_key(key: str, info: dict, root: Path) -> None:
    if not isinstance(key, str) or not key or "/" in key or key.startswith(".") or key != key.strip():
        raise InputError(f"video key {key!r}: must be a non-empty name without '/' (LeRobot's stats separator)")
    if key in info["features"]:
        raise InputError(f"{root}: feature {key!r} already exists")
    if (root / VIDEOS_DIR / key).exists():
        raise InputError(f"{root}: videos/{key} exists but {key!r} is not a feature (left over from an "
                         "interrupted run?); remove that directory first")


# ----------------------------------------------------------------------------- one stream


class _Stream:
    """Everything written for one key: files, per-episode location and stats."""

    def __init__(self, key: str, encoding: VideoEncoding, fps: int, tmp_root: Path, video_path: str,
                 chunks_size: int, max_file_bytes: float, depth_map: DepthMapParams | None = None):
        self.key, self.encoding, self.fps = key, encoding, fps
        self.depth_map = depth_map  # a LeRobot depth map's quantiser: frames are its 12-bit codes
        self.tmp_root, self.video_path = tmp_root, video_path
        self.chunks_size, self.max_file_bytes = chunks_size, max_file_bytes
        self.hw: tuple[int, int] | None = None
        self.chunk, self.file = 0, 0
        self.writer: VideoWriter | None = None
        self.episodes_in_file = 0
        self.rows: dict[int, dict] = {}  # episode index -> location + stats
        self.first_file: Path | None = None
        self.episode: int | None = None

    def _path(self) -> Path:
        return self.tmp_root / self.video_path.format(video_key=self.key, chunk_index=self.chunk,
                                                      file_index=self.file)

    def begin(self, ep_index: int, length: int) -> None:
        w = self.writer
        if w is not None and self.episodes_in_file > 0:
            predicted = w.bytes + w.bytes / self.episodes_in_file
            if predicted >= self.max_file_bytes:
                w.close()
                self.writer = None
                self.chunk, self.file = lr.update_chunk_file_indices(self.chunk, self.file, self.chunks_size)
        self.episode, self.length, self.n = ep_index, int(length), 0
        self.start = self.writer.frames if self.writer is not None else 0
        self.stats = ImageStats(self.length, None if self.depth_map is None else self.depth_map.code_values())
        self.where = f"episode {ep_index} {self.key!r}"

    def write(self, frames) -> None:
        if self.episode is None:
            raise RuntimeError(f"stream {self.key!r}: write() outside an episode")
        batches = frame_batches if self.depth_map is None else code_batches
        for batch in batches(frames, self.where):
            hw = (int(batch.shape[1]), int(batch.shape[2]))
            if self.hw is None:
                self.hw = hw
                if any(s in self.encoding.pix_fmt for s in SUBSAMPLED_CHROMA) and (hw[0] % 2 or hw[1] % 2):
                    raise InputError(f"{self.where}: {self.encoding.pix_fmt} needs even frame sizes, got {hw}")
            elif hw != self.hw:
                raise InputError(f"{self.where}: frame size {hw} differs from the stream's {self.hw} "
                                 "(all episodes of a stream must have one size)")
            if self.n + len(batch) > self.length:
                raise InputError(f"{self.where}: more frames than the episode's {self.length}")
            if self.writer is None:
                self.writer = VideoWriter(self._path(), self.encoding, self.fps, *self.hw,
                                          frame_format="rgb24" if self.depth_map is None else DEPTH_MAP_PIX_FMT)
                self.first_file = self.first_file or self.writer.path
                self.episodes_in_file = 0
                self.start = 0
            self.writer.write(batch)
            self.stats.update(batch)
            self.n += len(batch)

    def end(self) -> None:
        if self.n != self.length:
            raise InputError(f"{self.where}: {self.n} frames, but the episode has {self.length}")
        self.episodes_in_file += 1
        self.rows[self.episode] = {
            video_column(self.key, "chunk_index"): self.chunk,
            video_column(self.key, "file_index"): self.file,
            video_column(self.key, "from_timestamp"): self.start / self.fps,
            video_column(self.key, "to_timestamp"): (self.start + self.length) / self.fps,
            "stats": self.stats.normalised(),
        }
        self.episode = None

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
            self.writer = None

    def abort(self) -> None:
        if self.writer is not None:
            self.writer.abort()
            self.writer = None


# ----------------------------------------------------------------------------- the writer


class StreamWriter:
    """New video streams ``keys`` of the dataset at ``root``, written as frames arrive::

        with StreamWriter(root, keys, encodings) as streams:
            for ep in range(n_episodes):
                streams.begin_episode(ep)              # episodes in index order
                streams.write({key: frames, ...})      # any keys, (n, H, W, 3) uint8, as often as needed
                streams.end_episode()
            features = streams.commit()

    ``encodings``: one :class:`VideoEncoding` for all keys or one per key (default
    :meth:`VideoEncoding.lossless_rgb`). ``depth_maps[key]``: the quantiser of a key that is a
    LeRobot depth map (frames ``(n, H, W)`` uint16 codes, encoding in ``gray12le``, e.g.
    :meth:`VideoEncoding.depth_map`). ``info_extra[key]`` is merged into that feature's
    ``info`` block. ``imac_info`` (a mapping, or a function of the features written) is
    merged into the ``imac`` block (``meta/imac/info.json``) in the same write. ``threads``:
    keys encoded in parallel by :meth:`write` (each encoder's own output does not depend on it).
    Leaving the ``with`` block without :meth:`commit` (or on an error) discards everything.
    """

    def __init__(self, root: str | Path, keys: Sequence[str], encodings=None, *,
                 info_extra: Mapping[str, Mapping[str, Any]] | None = None,
                 imac_info: Mapping[str, Any] | Callable[[dict[str, dict]], Mapping[str, Any]] | None = None,
                 threads: int = 1, depth_maps: Mapping[str, DepthMapParams] | None = None):
        self.root = Path(root)
        info = read_v3_info(self.root)
        keys = list(keys)
        if not keys:
            raise InputError("add_video_streams: no keys given")
        if len(set(keys)) != len(keys):
            raise InputError(f"add_video_streams: duplicate keys in {keys}")
        for key in keys:
            _check_key(key, info, self.root)
        if encodings is None:
            encodings = VideoEncoding.lossless_rgb()
        if isinstance(encodings, VideoEncoding):
            encodings = {k: encodings for k in keys}
        missing = [k for k in keys if not isinstance(encodings.get(k), VideoEncoding)]
        if missing:
            raise InputError(f"add_video_streams: no VideoEncoding for {missing}")
        depth_maps = dict(depth_maps or {})
        for key, params in depth_maps.items():
            if key not in keys or not isinstance(params, DepthMapParams):
                raise InputError(f"add_video_streams: depth_maps[{key!r}] must be a DepthMapParams of an added key")
            if encodings[key].pix_fmt != DEPTH_MAP_PIX_FMT:
                raise InputError(f"add_video_streams: depth map {key!r} needs a {DEPTH_MAP_PIX_FMT} encoding, got "
                                 f"{encodings[key].pix_fmt}")
        self.info_extra = dict(info_extra or {})
        unknown = sorted(set(self.info_extra) - set(keys))
        if unknown:
            raise InputError(f"add_video_streams: info_extra for keys that are not added: {unknown}")
        self.keys, self.imac_info = keys, imac_info
        self.fps = int(info["fps"])
        self.video_path = info.get("video_path") or DEFAULT_VIDEO_PATH
        max_bytes = float(info.get("video_files_size_in_mb", 200)) * 1024 * 1024
        chunks_size = int(info.get("chunks_size", 1000))
        self.tmp = self.root / f".imac-tmp-{uuid.uuid4().hex[:12]}"
        self.tmp.mkdir()
        self.streams = {k: _Stream(k, encodings[k], self.fps, self.tmp, self.video_path, chunks_size, max_bytes,
                                   depth_maps.get(k)) for k in keys}
        self.episodes_done = 0
        self._lengths: dict[int, int] | None = None
        self._pool = ThreadPoolExecutor(max_workers=threads) if threads > 1 else None
        self._episode_open = False
        self._closed = False

    def __enter__(self) -> StreamWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if not self._closed:
            self.abort()

    # ------------------------------------------------------------------ episodes

    def begin_episode(self, ep_index: int, length: int | None = None) -> None:
        """Start episode ``ep_index`` (the next in index order) of ``length`` frames (default:
        the length in ``meta/episodes``)."""
        if self._episode_open:
            raise RuntimeError("begin_episode() while an episode is open")
        if ep_index != self.episodes_done:
            raise InputError(f"episodes must come in index order: got {ep_index}, expected {self.episodes_done}")
        if length is None:
            if self._lengths is None:
                self._lengths = episode_lengths(self.root)
            if ep_index not in self._lengths:
                raise InputError(f"got more episodes than the dataset's {len(self._lengths)}")
            length = self._lengths[ep_index]
        for s in self.streams.values():
            s.begin(ep_index, length)
        self._episode_open = True

    def write(self, frames: Mapping[str, Any]) -> None:
        """Frames of the open episode for some keys: ``{key: (n, H, W, 3) uint8}`` (numpy or torch;
        depth maps ``(n, H, W)`` uint16 codes)."""
        unknown = sorted(set(frames) - set(self.keys))
        if unknown:
            raise InputError(f"episode {self.episodes_done}: keys {unknown} are not streams of this writer "
                             f"({self.keys})")
        if self._pool is None or len(frames) == 1:
            for key, f in frames.items():
                self.streams[key].write(f)
        else:
            for job in [self._pool.submit(self.streams[k].write, f) for k, f in frames.items()]:
                job.result()

    def end_episode(self) -> None:
        for s in self.streams.values():
            s.end()
        self._episode_open = False
        self.episodes_done += 1

    # ------------------------------------------------------------------ commit

    def commit(self) -> dict[str, dict]:
        """Register the streams in the dataset (metadata replaced atomically, ``info.json``
        last). Returns the feature dicts written."""
        import pyarrow.parquet as pq

        if self._episode_open:
            raise RuntimeError("commit() while an episode is open")
        root, tmp = self.root, self.tmp
        moved: list[Path] = []
        backups: list[tuple[Path, Path]] = []
        created: list[Path] = []
        try:
            info = read_v3_info(root)
            lengths = episode_lengths(root)
            n_episodes = int(info["total_episodes"])
            if sorted(lengths) != list(range(n_episodes)):
                raise InputError(f"{root}: meta/episodes lists episodes {sorted(lengths)[:10]}..., "
                                 f"expected 0..{n_episodes - 1}")
            if self.episodes_done != n_episodes:
                raise InputError(f"got frames for {self.episodes_done} episodes; the dataset has {n_episodes}")
            for s in self.streams.values():
                for ep, row in s.rows.items():
                    n = round((row[video_column(s.key, "to_timestamp")] - row[video_column(s.key, "from_timestamp")]) * s.fps)
                    if n != lengths[ep]:
                        raise InputError(f"episode {ep} {s.key!r}: {n} frames, but the episode has {lengths[ep]}")
            for s in self.streams.values():
                s.close()

            # 1. metadata, written next to the originals first
            features = {}
            for key, s in self.streams.items():
                h, w = s.hw
                if s.depth_map is not None:  # exactly LeRobot 0.6's form, so that its tools read it
                    block = depth_map_video_info(s.first_file, s.encoding, s.depth_map)
                else:
                    block = video_info(s.first_file)
                    block["imac.encoding"] = s.encoding.to_dict()
                block.update(self.info_extra.get(key, {}))
                features[key] = {"dtype": "video", "shape": [h, w, 1 if s.depth_map is not None else 3],
                                 "names": ["height", "width", "channels"], "info": block}
            new_info = json.loads(json.dumps(info))
            new_info["features"].update(features)
            new_info["video_path"] = self.video_path
            if self.imac_info is not None:
                block = self.imac_info(features) if callable(self.imac_info) else self.imac_info
                new_info.setdefault("imac", {}).update(json.loads(json.dumps(block)))

            stats_file = stats_path(root)
            stats = json.loads(stats_file.read_text()) if stats_file.is_file() else {}
            for key, s in self.streams.items():
                agg = lr.aggregate_stats([{key: s.rows[i]["stats"]} for i in range(n_episodes)])
                stats.update(lr.serialize_dict(agg))

            staged: list[tuple[Path, Path]] = []  # (new file in tmp, destination)
            for f in episode_files(root):
                table = _episode_table_with(pq.read_table(f), list(self.streams.values()))
                out = tmp / "meta" / f.relative_to(root / "meta")
                out.parent.mkdir(parents=True, exist_ok=True)
                pq.write_table(table, out)
                staged.append((out, f))
            (tmp / "stats.json").write_text(json.dumps(stats, indent=4))
            staged.append((tmp / "stats.json", stats_file))
            staged += stage_info(root, new_info, tmp)  # the imac block to meta/imac/info.json, info.json last

            # 2. commit: new video dirs, then metadata (info.json last), with backups
            for key in self.keys:
                dst = root / VIDEOS_DIR / key
                dst.parent.mkdir(parents=True, exist_ok=True)
                os.rename(tmp / VIDEOS_DIR / key, dst)
                moved.append(dst)
            backup_dir = tmp / "backup"
            backup_dir.mkdir()
            for i, (new, dst) in enumerate(staged):
                existed = dst.exists()
                bak = backup_dir / f"{i}-{dst.name}"
                if existed:
                    shutil.copy2(dst, bak)
                else:
                    dst.parent.mkdir(parents=True, exist_ok=True)  # meta/imac/ of a dataset without a block yet
                os.replace(new, dst)
                if existed:
                    backups.append((bak, dst))
                else:
                    created.append(dst)
        except BaseException:
            for bak, dst in backups:
                with suppress(OSError):
                    os.replace(bak, dst)
            for dst in created:
                with suppress(OSError):
                    dst.unlink()
            for d in moved:
                shutil.rmtree(d, ignore_errors=True)
            self.abort()
            raise
        self._close()
        return features

    def abort(self) -> None:
        """Discard everything written so far (the dataset is left as it was)."""
        for s in self.streams.values():
            s.abort()
        self._close()

    def _close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True)
        shutil.rmtree(self.tmp, ignore_errors=True)
        self._closed = True


def _episode_table_with(table, streams: Sequence[_Stream]):
    import pyarrow as pa

    ep = table.column("episode_index").to_pylist()
    loc, stat = [], []
    for s in streams:
        rows = [s.rows[i] for i in ep]
        for suffix, typ in (("chunk_index", pa.int64()), ("file_index", pa.int64()),
                            ("from_timestamp", pa.float64()), ("to_timestamp", pa.float64())):
            col = video_column(s.key, suffix)
            loc.append((col, pa.array([r[col] for r in rows], type=typ)))
        for name in STAT_KEYS:
            typ = pa.list_(pa.int64()) if name == "count" else pa.list_(pa.list_(pa.list_(pa.float64())))
            stat.append((stats_column(s.key, name), pa.array([r["stats"][name].tolist() for r in rows], type=typ)))
    table = insert_columns_after(table, VIDEO_COLUMNS, "dataset_to_index", loc)
    return insert_columns_after(table, STATS_COLUMNS, "dataset_to_index", stat)


# ----------------------------------------------------------------------------- whole episodes


def add_video_streams(
    root: str | Path,
    episodes: Iterable[Mapping[str, Any]],
    *,
    keys: Sequence[str],
    encodings: VideoEncoding | Mapping[str, VideoEncoding] | None = None,
    info_extra: Mapping[str, Mapping[str, Any]] | None = None,
    imac_info: Mapping[str, Any] | Callable[[dict[str, dict]], Mapping[str, Any]] | None = None,
    progress: bool = False,
) -> dict[str, dict]:
    """Add video features ``keys`` to the LeRobot v3.0 dataset at ``root``.

    ``episodes`` yields, in episode-index order (0, 1, ...), one mapping per episode
    ``{key: frames}`` with every key; ``frames`` is uint8 RGB ``(T, H, W, 3)`` or an
    iterable of frames ``(H, W, 3)`` / chunks ``(n, H, W, 3)`` (consumed lazily: memory
    stays bounded by one chunk). ``T`` must equal the episode's length; all episodes of a
    key must have one frame size (it may differ from the other cameras'). Settings as
    :class:`StreamWriter`. Raises :class:`InputError` for bad input; on any error the
    dataset is left as it was.
    """
    from tqdm.auto import tqdm

    with StreamWriter(root, keys, encodings, info_extra=info_extra, imac_info=imac_info) as writer:
        iterator = iter(episodes) if isinstance(episodes, Iterable) else None
        if iterator is None:
            raise InputError(f"episodes must be an iterable of per-episode mappings, got {type(episodes).__name__}")
        for ep_index, item in enumerate(tqdm(iterator, desc="encode streams", unit="ep", disable=not progress)):
            if not isinstance(item, Mapping):
                raise InputError(f"episode {ep_index}: expected a mapping {{key: frames}}, got {type(item).__name__}")
            if set(item) != set(writer.keys):
                raise InputError(f"episode {ep_index}: has keys {sorted(item)}, expected {sorted(writer.keys)}")
            writer.begin_episode(ep_index)
            for key in writer.keys:
                writer.write({key: item[key]})
            writer.end_episode()
        return writer.commit()


def add_video_stream(root: str | Path, key: str, episodes: Iterable[Any], *,
                     encoding: VideoEncoding | None = None, info_extra: Mapping[str, Any] | None = None,
                     imac_info=None, progress: bool = False) -> dict:
    """One stream: ``episodes`` yields each episode's frames (see :func:`add_video_streams`)."""
    features = add_video_streams(
        root, ({key: frames} for frames in episodes), keys=[key], encodings=encoding,
        info_extra={key: info_extra} if info_extra else None, imac_info=imac_info, progress=progress,
    )
    return features[key]
