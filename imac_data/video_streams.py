"""Add video streams to an existing LeRobot v3.0 dataset.

LeRobot 0.4.4 can add parquet columns to a dataset but not a video stream. This
module does it by hand, laid out exactly as LeRobot 0.4.4 itself writes video
features (``lerobot_dataset.py`` ``_save_episode_video`` / ``save_episode``,
``compute_stats.py``), so ``LeRobotDataset`` (default decoder: torchcodec),
``delta_timestamps`` and ``aggregate_datasets`` treat the new stream like any
camera:

* mp4 files under ``info["video_path"]`` (``videos/<key>/chunk-XXX/file-YYY.mp4``).
  Consecutive episodes share a file (one continuous encoder session, frame ``i``
  of the file at ``pts = i / fps``); a new file starts when the next episode
  would push the file past ``info["video_files_size_in_mb"]`` (predicted from the
  file's mean bytes per episode so far), and a new chunk after
  ``info["chunks_size"]`` files, as LeRobot does;
* per episode in ``meta/episodes/*.parquet``: ``videos/<key>/chunk_index``,
  ``file_index``, ``from_timestamp``, ``to_timestamp`` (seconds in the file; the
  episode's frame ``k`` is at ``from_timestamp + k / fps``) and the episode stats
  ``stats/<key>/{min,max,mean,std,count,q01,q10,q50,q90,q99}``;
* ``meta/info.json``: the feature ``{"dtype": "video", "shape": [H, W, 3],
  "names": ["height", "width", "channels"], "info": {...}}``; the ``info`` block is
  what LeRobot's ``get_video_info`` reads from the first file, plus
  ``"imac.encoding"`` (our encoder settings) and any caller keys;
* ``meta/stats.json``: the stream's stats aggregated over episodes with LeRobot's
  ``aggregate_stats``.

Stats follow LeRobot's image stats exactly: per channel, shape ``(3, 1, 1)``,
normalised to ``[0, 1]``, computed by ``compute_stats.get_feature_stats`` over the
frames LeRobot's ``sample_indices`` picks, downsampled by
``auto_downsample_height_width``; ``count`` is the number of sampled frames. One
deliberate difference: we compute them in float64. LeRobot 0.4.4 passes uint8
pixels to its running-stats class, whose ``batch**2`` overflows in uint8, so the
``std`` LeRobot writes for its own image streams is wrong (often 0); ours is right.

Encoding is our own PyAV encoder with explicit settings (:class:`VideoEncoding`),
not LeRobot's (fixed at yuv420p, crf 30, which destroys colour-coded data).

Safety:

* existing files are never opened for writing: the original camera streams stay
  byte-identical;
* everything is encoded into a temporary directory inside the dataset; the
  metadata files are replaced (``os.replace``) only after every episode was
  encoded and checked, ``meta/info.json`` last (it is what makes LeRobot see the
  stream). On any error the temporary files are removed and replaced metadata is
  restored, so the dataset is left as it was;
* :func:`staged_dataset` gives a private copy to write several streams into and
  swaps it into place at the end (for multi-step augmentation).

Typical use::

    enc = VideoEncoding.lossless_rgb()
    add_video_streams(root, ({"control.motion.cam_high": frames_of(ep)} for ep in range(n)),
                      keys=["control.motion.cam_high"], encodings=enc)
"""

from __future__ import annotations

import json
import os
import shutil
import sys
import uuid
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from contextlib import contextmanager, suppress
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np

from imac_data.errors import InputError

__all__ = [
    "VideoEncoding",
    "add_video_stream",
    "add_video_streams",
    "encode_video",
    "read_video_frames",
    "staged_dataset",
]

DEFAULT_VIDEO_PATH = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
_STAT_KEYS = ("min", "max", "mean", "std", "count", "q01", "q10", "q50", "q90", "q99")
_SUBSAMPLED_CHROMA = ("420", "422", "411", "410", "nv12", "nv21", "nv16")


# ----------------------------------------------------------------------------- settings
@dataclass(frozen=True)
class VideoEncoding:
    """Explicit encoder settings for one stream (all recorded in the dataset).

    ``codec`` is an FFmpeg encoder name as PyAV knows it (``libx264rgb``,
    ``libx264``, ``libsvtav1``, ...), ``pix_fmt`` the pixel format the stream is
    coded in (frames are given as RGB24; PyAV converts). ``crf`` / ``qp`` / ``preset``
    / ``gop`` map to the FFmpeg options ``crf``, ``qp``, ``preset``, ``g``;
    ``options`` adds any other encoder option (strings). ``None`` leaves the
    encoder's default.
    """

    codec: str = "libx264rgb"
    pix_fmt: str = "rgb24"
    crf: int | None = None
    qp: int | None = 0
    preset: str | int | None = "medium"
    gop: int | None = 10
    options: Mapping[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        import av

        if not isinstance(self.codec, str) or not self.codec:
            raise InputError(f"VideoEncoding.codec must be an encoder name, got {self.codec!r}")
        try:
            codec = av.codec.Codec(self.codec, "w")
        except Exception:
            raise InputError(
                f"VideoEncoding.codec: encoder {self.codec!r} is not available in this PyAV/FFmpeg build"
            ) from None
        if codec.type != "video":
            raise InputError(f"VideoEncoding.codec: {self.codec!r} is not a video encoder")
        formats = [f.name for f in (codec.video_formats or [])]
        if not isinstance(self.pix_fmt, str) or (formats and self.pix_fmt not in formats):
            raise InputError(
                f"VideoEncoding.pix_fmt: encoder {self.codec!r} does not take {self.pix_fmt!r}; it takes {formats}"
            )
        for name in ("crf", "qp", "gop"):
            value = getattr(self, name)
            if value is not None and (isinstance(value, bool) or not isinstance(value, (int, np.integer))
                                      or value < (1 if name == "gop" else 0)):
                raise InputError(f"VideoEncoding.{name} must be None or an integer >= "
                                 f"{1 if name == 'gop' else 0}, got {value!r}")
        if self.crf is not None and self.qp is not None:
            raise InputError("VideoEncoding: give crf or qp, not both")
        if self.preset is not None and (isinstance(self.preset, bool) or not isinstance(self.preset, (str, int))):
            raise InputError(f"VideoEncoding.preset must be None, a string or an integer, got {self.preset!r}")
        if not isinstance(self.options, Mapping):
            raise InputError(f"VideoEncoding.options must be a mapping of strings, got {type(self.options).__name__}")
        options = {str(k): str(v) for k, v in self.options.items()}
        for reserved in ("g", "crf", "qp", "preset"):
            if reserved in options:
                raise InputError(f"VideoEncoding.options: set {reserved!r} with its own field, not in options")
        object.__setattr__(self, "options", dict(sorted(options.items())))

    @classmethod
    def lossless_rgb(cls, gop: int = 10, preset: str = "medium") -> VideoEncoding:
        """H.264 in RGB (libx264rgb, stored as planar GBR), qp 0: bit-exact RGB.

        The depth stream's settings (chosen by measurement, see
        ``benchmarks/depth_fidelity.py``): bit-exact through torchcodec and PyAV, about
        4.7-5.3 KB per 240x320 depth frame at gop 10.
        """
        return cls(codec="libx264rgb", pix_fmt="rgb24", qp=0, crf=None, preset=preset, gop=gop)

    @classmethod
    def lerobot_default(cls) -> VideoEncoding:
        """What LeRobot 0.4.4 writes for its cameras: libsvtav1, yuv420p, crf 30, gop 2, preset 12."""
        return cls(codec="libsvtav1", pix_fmt="yuv420p", crf=30, qp=None, preset=12, gop=2)

    def encoder_options(self) -> dict[str, str]:
        """The FFmpeg options passed to the encoder."""
        opts: dict[str, str] = {}
        if self.gop is not None:
            opts["g"] = str(self.gop)
        if self.crf is not None:
            opts["crf"] = str(self.crf)
        if self.qp is not None:
            opts["qp"] = str(self.qp)
        if self.preset is not None:
            opts["preset"] = str(self.preset)
        opts.update(self.options)
        return opts

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready settings (deterministic: no library versions, so two datasets
        built with the same settings get identical feature dicts, as
        ``aggregate_datasets`` requires). See :func:`encoder_versions`."""
        return {
            "codec": self.codec, "pix_fmt": self.pix_fmt, "crf": self.crf, "qp": self.qp,
            "preset": self.preset, "gop": self.gop, "options": dict(self.options),
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> VideoEncoding:
        if not isinstance(d, Mapping) or "codec" not in d:
            raise InputError(f"video encoding metadata must be a mapping with a 'codec' key, got {d!r}")
        known = {"codec", "pix_fmt", "crf", "qp", "preset", "gop", "options"}
        return cls(**{k: v for k, v in d.items() if k in known})


def encoder_versions() -> dict[str, str]:
    """Versions of the libraries that encoded (for ``info["imac"]``, not the feature dict)."""
    import av

    libs = {name: ".".join(map(str, v)) for name, v in av.library_versions.items() if name == "libavcodec"}
    return {"pyav": av.__version__, **libs}


# ------------------------------------------------------------------------------- frames
def _is_torch(x) -> bool:
    torch = sys.modules.get("torch")
    return torch is not None and isinstance(x, torch.Tensor)


def _frame_batches(frames, where: str) -> Iterator[np.ndarray]:
    """Frames as ``(n, H, W, 3)`` arrays: accepts one array ``(T, H, W, 3)``, or an
    iterable of frames ``(H, W, 3)`` and/or chunks ``(n, H, W, 3)`` (numpy or torch)."""

    def as_batch(x):
        if _is_torch(x):
            x = x.detach().cpu().numpy()
        if not isinstance(x, np.ndarray):
            raise InputError(f"{where}: frames must be numpy arrays (or torch tensors), got {type(x).__name__}")
        if x.ndim == 3:
            x = x[None]
        if x.ndim != 4 or x.shape[-1] != 3:
            raise InputError(f"{where}: frames must be (H, W, 3) or (T, H, W, 3) RGB; got shape {x.shape}")
        if x.dtype != np.uint8:
            raise InputError(f"{where}: frames must be uint8 (0..255); got {x.dtype}")
        return x

    if isinstance(frames, np.ndarray) or _is_torch(frames):
        yield as_batch(frames)
        return
    if isinstance(frames, (str, bytes)) or not isinstance(frames, Iterable):
        raise InputError(f"{where}: expected an array or an iterable of frames, got {type(frames).__name__}")
    for item in frames:
        yield as_batch(item)


# ------------------------------------------------------------------------------ encoding
@contextmanager
def _quiet_libav():
    """FFmpeg's own log at ERROR while we encode (x264 prints its statistics at INFO);
    the previous level is restored."""
    import av.logging

    previous = av.logging.get_level()
    av.logging.set_level(av.logging.ERROR)
    try:
        yield
    finally:
        av.logging.set_level(previous)


class _FileWriter:
    """One mp4 being written: a continuous encoder session (pts = frame index)."""

    def __init__(self, path: Path, encoding: VideoEncoding, fps: int, height: int, width: int):
        import av

        path.parent.mkdir(parents=True, exist_ok=True)
        self.path = path
        self.container = av.open(str(path), mode="w", format="mp4",
                                 container_options={"movflags": "faststart"})
        try:
            self.stream = self.container.add_stream(encoding.codec, rate=fps, options=encoding.encoder_options())
            self.stream.width = width
            self.stream.height = height
            self.stream.pix_fmt = encoding.pix_fmt
            self.stream.time_base = Fraction(1, fps)
        except Exception:
            self.container.close()
            raise
        self.time_base = Fraction(1, fps)
        self.frames = 0
        self.bytes = 0

    def write(self, batch: np.ndarray) -> None:
        import av

        for frame in batch:
            vf = av.VideoFrame.from_ndarray(np.ascontiguousarray(frame), format="rgb24")
            vf.pts = self.frames
            vf.time_base = self.time_base
            self._mux(self.stream.encode(vf))
            self.frames += 1

    def _mux(self, packets) -> None:
        for packet in packets:
            self.bytes += packet.size
            self.container.mux(packet)

    def close(self) -> None:
        try:
            self._mux(self.stream.encode(None))
        finally:
            self.container.close()

    def abort(self) -> None:
        try:
            self.container.close()
        except Exception:  # noqa: BLE001 - already failing; the file is deleted anyway
            pass


def encode_video(path: str | Path, frames, *, fps: int, encoding: VideoEncoding | None = None) -> Path:
    """Encode ``frames`` (uint8 RGB ``(T, H, W, 3)`` or an iterable of frames / chunks)
    into a new mp4 at ``path`` with ``encoding`` (default :meth:`VideoEncoding.lossless_rgb`).
    For benchmarks and one-off files; datasets use :func:`add_video_streams`."""
    path = Path(path)
    encoding = encoding or VideoEncoding.lossless_rgb()
    writer = None
    try:
        with _quiet_libav():
            for batch in _frame_batches(frames, str(path)):
                if writer is None:
                    writer = _FileWriter(path, encoding, int(fps), batch.shape[1], batch.shape[2])
                writer.write(batch)
            if writer is None:
                raise InputError(f"{path}: no frames to encode")
            writer.close()
    except BaseException:
        if writer is not None:
            writer.abort()
        path.unlink(missing_ok=True)
        raise
    return path


def read_video_frames(path: str | Path) -> np.ndarray:
    """All frames of a video as uint8 RGB ``(T, H, W, 3)``, decoded with PyAV."""
    import av

    with av.open(str(path)) as container:
        return np.stack([f.to_ndarray(format="rgb24") for f in container.decode(video=0)])


class _StreamState:
    """Everything written for one key: files, per-episode location and stats."""

    def __init__(self, key: str, encoding: VideoEncoding, fps: int, tmp_root: Path, video_path: str,
                 chunks_size: int, max_file_bytes: float):
        self.key = key
        self.encoding = encoding
        self.fps = fps
        self.tmp_root = tmp_root
        self.video_path = video_path
        self.chunks_size = chunks_size
        self.max_file_bytes = max_file_bytes
        self.hw: tuple[int, int] | None = None
        self.chunk, self.file = 0, 0
        self.writer: _FileWriter | None = None
        self.episodes_in_file = 0
        self.files: list[Path] = []
        self.rows: dict[int, dict] = {}  # episode index -> location + stats
        self.first_file: Path | None = None

    def _path(self) -> Path:
        return self.tmp_root / self.video_path.format(video_key=self.key, chunk_index=self.chunk,
                                                      file_index=self.file)

    def write_episode(self, ep_index: int, length: int, frames, where: str) -> None:
        from lerobot.datasets.compute_stats import auto_downsample_height_width, sample_indices
        from lerobot.datasets.utils import update_chunk_file_indices

        w = self.writer
        if w is not None and self.episodes_in_file > 0:
            predicted = w.bytes + w.bytes / self.episodes_in_file
            if predicted >= self.max_file_bytes:
                w.close()
                self.writer = None
                self.chunk, self.file = update_chunk_file_indices(self.chunk, self.file, self.chunks_size)
        start = self.writer.frames if self.writer is not None else 0
        wanted = set(sample_indices(length)) if length > 0 else set()
        samples = []
        n = 0
        for batch in _frame_batches(frames, where):
            hw = (int(batch.shape[1]), int(batch.shape[2]))
            if self.hw is None:
                self.hw = hw
                if any(s in self.encoding.pix_fmt for s in _SUBSAMPLED_CHROMA) and (hw[0] % 2 or hw[1] % 2):
                    raise InputError(f"{where}: {self.encoding.pix_fmt} needs even frame sizes, got {hw}")
            elif hw != self.hw:
                raise InputError(f"{where}: frame size {hw} differs from the stream's {self.hw} "
                                 "(all episodes of a stream must have one size)")
            if n + len(batch) > length:
                raise InputError(f"{where}: more frames than the episode's {length}")
            if self.writer is None:
                self.writer = _FileWriter(self._path(), self.encoding, self.fps, *self.hw)
                self.files.append(self.writer.path)
                self.first_file = self.first_file or self.writer.path
                self.episodes_in_file = 0
                start = 0
            self.writer.write(batch)
            for i in range(len(batch)):
                if n + i in wanted:
                    samples.append(auto_downsample_height_width(batch[i].transpose(2, 0, 1)))
            n += len(batch)
        if n != length:
            raise InputError(f"{where}: {n} frames, but the episode has {length}")
        self.episodes_in_file += 1
        self.rows[ep_index] = {
            f"videos/{self.key}/chunk_index": self.chunk,
            f"videos/{self.key}/file_index": self.file,
            f"videos/{self.key}/from_timestamp": start / self.fps,
            f"videos/{self.key}/to_timestamp": (start + length) / self.fps,
            "stats": _image_stats(np.stack(samples)),
        }

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
            self.writer = None

    def abort(self) -> None:
        if self.writer is not None:
            self.writer.abort()
            self.writer = None


def _image_stats(samples: np.ndarray) -> dict[str, np.ndarray]:
    """LeRobot's ``compute_episode_stats`` for an image/video feature, in float64.

    ``samples``: uint8 ``(n, 3, h, w)``. Returns ``(3, 1, 1)`` arrays in [0, 1] and
    ``count`` = ``[n]``.
    """
    from lerobot.datasets.compute_stats import get_feature_stats

    stats = get_feature_stats(samples.astype(np.float64), axis=(0, 2, 3), keepdims=True)
    return {k: v if k == "count" else np.squeeze(v / 255.0, axis=0) for k, v in stats.items()}


# -------------------------------------------------------------------------------- dataset
def _read_info(root: Path) -> dict:
    path = root / "meta" / "info.json"
    if not path.is_file():
        raise InputError(f"{root} is not a LeRobot dataset: {path} is missing")
    info = json.loads(path.read_text())
    if info.get("codebase_version") != "v3.0":
        raise InputError(f"{root}: dataset format {info.get('codebase_version')!r}; only LeRobot v3.0 is supported")
    return info


def _episode_files(root: Path) -> list[Path]:
    files = sorted((root / "meta" / "episodes").glob("*/*.parquet"))
    if not files:
        raise InputError(f"{root}: no meta/episodes/*/*.parquet files")
    return files


def _episode_lengths(files: Sequence[Path]) -> dict[int, int]:
    import pyarrow.parquet as pq

    lengths: dict[int, int] = {}
    for f in files:
        t = pq.read_table(f, columns=["episode_index", "length"])
        lengths.update(zip(t.column("episode_index").to_pylist(), t.column("length").to_pylist()))
    return lengths


def _check_key(key: str, info: dict, root: Path) -> None:
    if not isinstance(key, str) or not key or "/" in key or key.startswith(".") or key != key.strip():
        raise InputError(f"video key {key!r}: must be a non-empty name without '/' (LeRobot's stats separator)")
    if key in info["features"]:
        raise InputError(f"{root}: feature {key!r} already exists")
    if (root / "videos" / key).exists():
        raise InputError(f"{root}: videos/{key} exists but {key!r} is not a feature (left over from an "
                         "interrupted run?); remove that directory first")


def _insert_after(table, after_prefix: str, fallback: str, columns: list[tuple[str, Any]]):
    """Insert columns after the last column starting with ``after_prefix`` (else after
    ``fallback``, else at the end), keeping LeRobot's column order."""
    names = table.column_names
    idx = [i for i, n in enumerate(names) if n.startswith(after_prefix)]
    pos = (idx[-1] + 1) if idx else (names.index(fallback) + 1 if fallback in names else len(names))
    for offset, (name, array) in enumerate(columns):
        table = table.add_column(pos + offset, name, array)
    return table


def _episode_table_with(table, states: Sequence[_StreamState]):
    import pyarrow as pa

    ep = table.column("episode_index").to_pylist()
    loc, stat = [], []
    for s in states:
        rows = [s.rows[i] for i in ep]
        for suffix, typ in (("chunk_index", pa.int64()), ("file_index", pa.int64()),
                            ("from_timestamp", pa.float64()), ("to_timestamp", pa.float64())):
            col = f"videos/{s.key}/{suffix}"
            loc.append((col, pa.array([r[col] for r in rows], type=typ)))
        for name in _STAT_KEYS:
            typ = pa.list_(pa.int64()) if name == "count" else pa.list_(pa.list_(pa.list_(pa.float64())))
            stat.append((f"stats/{s.key}/{name}", pa.array([r["stats"][name].tolist() for r in rows], type=typ)))
    table = _insert_after(table, "videos/", "dataset_to_index", loc)
    return _insert_after(table, "stats/", "dataset_to_index", stat)


def _video_info(path: Path) -> dict[str, Any]:
    """The keys LeRobot's ``get_video_info`` writes, read the same way. (Its own
    function cannot be used: it raises on planar RGB ``gbrp``, which libx264rgb writes.)"""
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

    ``episodes`` yields, in episode-index order (0, 1, ...), one mapping per
    episode ``{key: frames}`` with every key; ``frames`` is uint8 RGB
    ``(T, H, W, 3)`` or an iterable of frames ``(H, W, 3)`` / chunks ``(n, H, W, 3)``
    (consumed lazily: memory stays bounded by one chunk). ``T`` must equal the
    episode's length; all episodes of a key must have one frame size (it may
    differ from the other cameras').

    ``encodings``: one :class:`VideoEncoding` for all keys or one per key (default
    :meth:`VideoEncoding.lossless_rgb`). ``info_extra[key]`` is merged into that
    feature's ``info`` block. ``imac_info`` (a mapping, or a function of the
    features written) is merged into ``info.json["imac"]`` in the same write.

    Returns the feature dicts written. Raises :class:`InputError` for bad input;
    on any error the dataset is left as it was.
    """
    with _quiet_libav():
        return _add_video_streams(root, episodes, keys, encodings, info_extra, imac_info, progress)


def _add_video_streams(root, episodes, keys, encodings, info_extra, imac_info, progress) -> dict[str, dict]:
    import pyarrow.parquet as pq
    from lerobot.datasets.compute_stats import aggregate_stats
    from lerobot.datasets.utils import serialize_dict
    from tqdm.auto import tqdm

    root = Path(root)
    info = _read_info(root)
    keys = list(keys)
    if not keys:
        raise InputError("add_video_streams: no keys given")
    if len(set(keys)) != len(keys):
        raise InputError(f"add_video_streams: duplicate keys in {keys}")
    for key in keys:
        _check_key(key, info, root)
    if encodings is None:
        encodings = VideoEncoding.lossless_rgb()
    if isinstance(encodings, VideoEncoding):
        encodings = {k: encodings for k in keys}
    missing = [k for k in keys if not isinstance(encodings.get(k), VideoEncoding)]
    if missing:
        raise InputError(f"add_video_streams: no VideoEncoding for {missing}")
    info_extra = dict(info_extra or {})
    unknown = sorted(set(info_extra) - set(keys))
    if unknown:
        raise InputError(f"add_video_streams: info_extra for keys that are not added: {unknown}")

    episode_files = _episode_files(root)
    lengths = _episode_lengths(episode_files)
    n_episodes = int(info["total_episodes"])
    if sorted(lengths) != list(range(n_episodes)):
        raise InputError(f"{root}: meta/episodes lists episodes {sorted(lengths)[:10]}..., "
                         f"expected 0..{n_episodes - 1}")
    fps = int(info["fps"])
    video_path = info.get("video_path") or DEFAULT_VIDEO_PATH
    max_bytes = float(info.get("video_files_size_in_mb", 200)) * 1024 * 1024
    chunks_size = int(info.get("chunks_size", 1000))

    tmp = root / f".imac-tmp-{uuid.uuid4().hex[:12]}"
    tmp.mkdir()
    states = {k: _StreamState(k, encodings[k], fps, tmp, video_path, chunks_size, max_bytes) for k in keys}
    moved: list[Path] = []
    backups: list[tuple[Path, Path]] = []
    created: list[Path] = []
    try:
        # 1. encode every episode of every stream into tmp/
        count = 0
        iterator = iter(episodes) if isinstance(episodes, Iterable) else None
        if iterator is None:
            raise InputError(f"episodes must be an iterable of per-episode mappings, got {type(episodes).__name__}")
        for ep_index, item in enumerate(tqdm(iterator, total=n_episodes, desc="encode streams", unit="ep",
                                             disable=not progress)):
            if ep_index >= n_episodes:
                raise InputError(f"got more episodes than the dataset's {n_episodes}")
            if not isinstance(item, Mapping):
                raise InputError(f"episode {ep_index}: expected a mapping {{key: frames}}, got {type(item).__name__}")
            if set(item) != set(keys):
                raise InputError(f"episode {ep_index}: has keys {sorted(item)}, expected {sorted(keys)}")
            for key in keys:
                states[key].write_episode(ep_index, lengths[ep_index], item[key], f"episode {ep_index} {key!r}")
            count += 1
        if count != n_episodes:
            raise InputError(f"got frames for {count} episodes; the dataset has {n_episodes}")
        for s in states.values():
            s.close()

        # 2. metadata, written next to the originals first
        features = {}
        for key, s in states.items():
            h, w = s.hw
            block = _video_info(s.first_file)
            block["imac.encoding"] = s.encoding.to_dict()
            block.update(info_extra.get(key, {}))
            features[key] = {"dtype": "video", "shape": [h, w, 3], "names": ["height", "width", "channels"],
                             "info": block}
        new_info = json.loads(json.dumps(info))
        new_info["features"].update(features)
        new_info["video_path"] = video_path
        if imac_info is not None:
            block = imac_info(features) if callable(imac_info) else imac_info
            new_info.setdefault("imac", {}).update(json.loads(json.dumps(block)))

        stats_path = root / "meta" / "stats.json"
        stats = json.loads(stats_path.read_text()) if stats_path.is_file() else {}
        for key, s in states.items():
            agg = aggregate_stats([{key: s.rows[i]["stats"]} for i in range(n_episodes)])
            stats.update(serialize_dict(agg))

        staged: list[tuple[Path, Path]] = []  # (new file in tmp, destination)
        for f in episode_files:
            table = _episode_table_with(pq.read_table(f), list(states.values()))
            out = tmp / "meta" / f.relative_to(root / "meta")
            out.parent.mkdir(parents=True, exist_ok=True)
            pq.write_table(table, out)
            staged.append((out, f))
        (tmp / "stats.json").write_text(json.dumps(stats, indent=4))
        staged.append((tmp / "stats.json", stats_path))
        (tmp / "info.json").write_text(json.dumps(new_info, indent=4))
        staged.append((tmp / "info.json", root / "meta" / "info.json"))

        # 3. commit: new video dirs, then metadata (info.json last), with backups
        for key in keys:
            src = tmp / "videos" / key
            dst = root / "videos" / key
            dst.parent.mkdir(parents=True, exist_ok=True)
            os.rename(src, dst)
            moved.append(dst)
        backup_dir = tmp / "backup"
        backup_dir.mkdir()
        for i, (new, dst) in enumerate(staged):
            existed = dst.exists()
            bak = backup_dir / f"{i}-{dst.name}"
            if existed:
                shutil.copy2(dst, bak)
            os.replace(new, dst)
            if existed:
                backups.append((bak, dst))
            else:
                created.append(dst)
    except BaseException:
        for s in states.values():
            s.abort()
        for bak, dst in backups:
            with suppress(OSError):
                os.replace(bak, dst)
        for dst in created:
            with suppress(OSError):
                dst.unlink()
        for d in moved:
            shutil.rmtree(d, ignore_errors=True)
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    shutil.rmtree(tmp, ignore_errors=True)
    return features


def add_video_stream(root: str | Path, key: str, episodes: Iterable[Any], *,
                     encoding: VideoEncoding | None = None, info_extra: Mapping[str, Any] | None = None,
                     imac_info=None, progress: bool = False) -> dict:
    """One stream: ``episodes`` yields each episode's frames (see :func:`add_video_streams`)."""
    features = add_video_streams(
        root, ({key: frames} for frames in episodes), keys=[key], encodings=encoding,
        info_extra={key: info_extra} if info_extra else None, imac_info=imac_info, progress=progress,
    )
    return features[key]


# ------------------------------------------------------------------------------ staging
def _link_or_copy(src: str, dst: str) -> None:
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)


@contextmanager
def staged_dataset(root: str | Path) -> Iterator[Path]:
    """A private copy of the dataset at ``root`` to write into; swapped into place
    when the ``with`` block ends without error, deleted otherwise::

        with staged_dataset(root) as work:
            add_video_streams(work, ...)
            add_video_streams(work, ...)

    The copy sits next to ``root`` (``.<name>.imac-staging``). Files under
    ``videos/`` are hard links to the originals (no copy of the big files), so code
    working in the copy must never modify an existing video file in place (this
    module only creates new ones); everything else is copied. The swap is two
    renames (``root`` -> ``.<name>.imac-old``, copy -> ``root``), then the old
    tree is deleted.
    """
    root = Path(root)
    _read_info(root)
    stage = root.parent / f".{root.name}.imac-staging"
    old = root.parent / f".{root.name}.imac-old"
    for leftover in (stage, old):
        if leftover.exists():
            shutil.rmtree(leftover)
    try:
        for entry in root.iterdir():
            dst = stage / entry.name
            if entry.is_dir():
                shutil.copytree(entry, dst, copy_function=_link_or_copy if entry.name == "videos" else shutil.copy2)
            else:
                stage.mkdir(parents=True, exist_ok=True)
                shutil.copy2(entry, dst)
        yield stage
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        raise
    os.rename(root, old)
    try:
        os.rename(stage, root)
    except BaseException:
        os.rename(old, root)
        shutil.rmtree(stage, ignore_errors=True)
        raise
    shutil.rmtree(old, ignore_errors=True)
