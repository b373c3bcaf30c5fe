"""Video encoding for dataset streams: settings, streaming mp4 writers, image statistics.

* :class:`VideoEncoding`: explicit encoder settings, recorded in the dataset.
* :class:`VideoWriter`: one mp4 written frame batch by frame batch (memory: the encoder's
  own buffers, never the episode). ``style="lerobot"`` writes exactly what LeRobot 0.4.4's
  ``encode_video_frames`` writes for its cameras (same container calls, same options: the
  files are byte-identical to LeRobot's PNG path, without the PNGs); ``style="imac"`` is
  our layout (explicit timestamps, ``faststart``).
* :class:`ImageStats`: LeRobot's per-episode image statistics (``compute_episode_stats``:
  frames at ``sample_indices``, downsampled by ``auto_downsample_height_width``, per channel
  min/max/mean/std/count and the q01..q99 of its 5000-bin histogram) computed exactly from
  per-channel value counts as the frames stream past, in float64; for a LeRobot depth map,
  of the metres its 12-bit codes decode to. Two differences from LeRobot, both deliberate:
  constant memory (LeRobot keeps every sampled frame), and a correct ``std`` (LeRobot 0.4.4
  squares uint8 pixels in uint8, so the ``std`` it writes for its own cameras overflows,
  often to 0).
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path
from typing import Any

import numpy as np

from imac_data import lerobot_compat as lr
from imac_data.console import native_stderr_silenced, scheduling_kept
from imac_data.core.depth_map import PIX_FMT as DEPTH_MAP_PIX_FMT
from imac_data.core.depth_map import QMAX
from imac_data.core.metric_depth import is_torch
from imac_data.errors import InputError

__all__ = ["VideoEncoding", "VideoWriter", "ImageStats", "encode_video", "read_video_frames", "encoder_versions",
           "frame_batches", "code_batches", "SUBSAMPLED_CHROMA"]

SUBSAMPLED_CHROMA = ("420", "422", "411", "410", "nv12", "nv21", "nv16")


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
    threads: int | None = None  # encoder threads (x264 ``threads``, SVT-AV1 ``lp``); None = the encoder's choice

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
        for name in ("crf", "qp", "gop", "threads"):
            value = getattr(self, name)
            if value is not None and (isinstance(value, bool) or not isinstance(value, (int, np.integer))
                                      or value < (1 if name in ("gop", "threads") else 0)):
                raise InputError(f"VideoEncoding.{name} must be None or an integer >= "
                                 f"{1 if name in ('gop', 'threads') else 0}, got {value!r}")
        if self.crf is not None and self.qp is not None:
            raise InputError("VideoEncoding: give crf or qp, not both")
        if self.preset is not None and (isinstance(self.preset, bool) or not isinstance(self.preset, (str, int))):
            raise InputError(f"VideoEncoding.preset must be None, a string or an integer, got {self.preset!r}")
        if not isinstance(self.options, Mapping):
            raise InputError(f"VideoEncoding.options must be a mapping of strings, got {type(self.options).__name__}")
        options = {str(k): str(v) for k, v in self.options.items()}
        for reserved in ("g", "crf", "qp", "preset", "threads", "svtav1-params"):
            if reserved in options:
                raise InputError(f"VideoEncoding.options: set {reserved!r} with its own field, not in options")
        object.__setattr__(self, "options", dict(sorted(options.items())))

    @classmethod
    def lossless_rgb(cls, gop: int = 10, preset: str = "ultrafast", threads: int = 1) -> VideoEncoding:
        """H.264 in RGB (libx264rgb, stored as planar GBR), qp 0: bit-exact RGB, the depth and
        control streams' settings (``benchmarks/depth_fidelity.py``). ``threads`` is fixed because
        x264's bytes depend on its thread count; one, because the pipeline already encodes its
        streams in parallel. Older datasets written with 2 threads decode to the same pixels.
        ``ultrafast``: a lossless stream decodes to the same values at any preset, and this one codes
        in an eighth of ``medium``'s CPU and decodes in half, at 1.9 times the bytes
        (``benchmarks/lossless_presets.py``); datasets built before 2026-12-01 used ``medium``."""
        return cls(codec="libx264rgb", pix_fmt="rgb24", qp=0, crf=None, preset=preset, gop=gop, threads=threads)

    @classmethod
    def depth_map(cls) -> VideoEncoding:
        """LeRobot 0.6's depth-map encoder (``DepthEncoderConfig``: HEVC, gray12le, gop 2, crf 30
        (unused when lossless), x265's default preset, ``lossless=1``) without B-frames (LeRobot
        0.4.4's torchcodec seeks them a frame off), with closed GOPs (every keyframe an IDR: in a
        file LeRobot concatenated, 0.6.1's PyAV reader seeking to the previous episode's last open
        keyframe fails on the next episode's first frame), on one x265 thread (bytes independent
        of the machine), x265's log at errors only."""
        return cls(codec="libx265", pix_fmt=DEPTH_MAP_PIX_FMT, crf=30, qp=None, preset=None, gop=2,
                   options={"x265-params": "lossless=1:bframes=0:open-gop=0:pools=none:frame-threads=1:"
                                           "log-level=error"})

    @classmethod
    def lerobot_default(cls) -> VideoEncoding:
        """What LeRobot 0.4.4 writes for its cameras: libsvtav1, yuv420p, crf 30, gop 2, preset 12."""
        return cls(codec="libsvtav1", pix_fmt="yuv420p", crf=30, qp=None, preset=12, gop=2)

    def encoder_options(self) -> dict[str, str]:
        """The FFmpeg options passed to the encoder (in LeRobot's order for its settings)."""
        opts: dict[str, str] = {}
        if self.gop is not None:
            opts["g"] = str(self.gop)
        if self.crf is not None:
            opts["crf"] = str(self.crf)
        if self.qp is not None:
            opts["qp"] = str(self.qp)
        if self.preset is not None:
            opts["preset"] = str(self.preset)
        if self.threads is not None:
            if self.codec == "libsvtav1":  # SVT-AV1's output does not depend on it (measured)
                opts["svtav1-params"] = f"lp={self.threads}"
            else:
                opts["threads"] = str(self.threads)
        opts.update(self.options)
        return opts

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready settings (deterministic: no library versions, so two datasets
        built with the same settings get identical feature dicts, as
        ``aggregate_datasets`` requires). See :func:`encoder_versions`."""
        d = {
            "codec": self.codec, "pix_fmt": self.pix_fmt, "crf": self.crf, "qp": self.qp,
            "preset": self.preset, "gop": self.gop, "options": dict(self.options),
        }
        if self.threads is not None and self.codec != "libsvtav1":  # part of what determines the bytes
            d["threads"] = self.threads
        return d

    def with_threads(self, threads: int | None) -> VideoEncoding:
        """The same settings with another thread count (use only where the output does not
        depend on it: SVT-AV1)."""
        from dataclasses import replace

        return replace(self, threads=threads)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> VideoEncoding:
        if not isinstance(d, Mapping) or "codec" not in d:
            raise InputError(f"video encoding metadata must be a mapping with a 'codec' key, got {d!r}")
        known = {"codec", "pix_fmt", "crf", "qp", "preset", "gop", "options", "threads"}
        return cls(**{k: v for k, v in d.items() if k in known})


def encoder_versions() -> dict[str, str]:
    """Versions of the libraries that encoded (for ``info["imac"]``, not the feature dict)."""
    import av

    libs = {name: ".".join(map(str, v)) for name, v in av.library_versions.items() if name == "libavcodec"}
    return {"pyav": av.__version__, **libs}


# ------------------------------------------------------------------------------- frames
def frame_batches(frames, where: str) -> Iterator[np.ndarray]:
    """Frames as ``(n, H, W, 3)`` arrays: accepts one array ``(T, H, W, 3)``, or an
    iterable of frames ``(H, W, 3)`` and/or chunks ``(n, H, W, 3)`` (numpy or torch)."""

    def as_batch(x):
        if is_torch(x):
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

    if isinstance(frames, np.ndarray) or is_torch(frames):
        yield as_batch(frames)
        return
    if isinstance(frames, (str, bytes)) or not isinstance(frames, Iterable):
        raise InputError(f"{where}: expected an array or an iterable of frames, got {type(frames).__name__}")
    for item in frames:
        yield as_batch(item)


def code_batches(frames, where: str) -> Iterator[np.ndarray]:
    """Depth-map frames as ``(n, H, W)`` uint16 12-bit codes: one array ``(T, H, W)`` or an
    iterable of frames ``(H, W)`` and/or chunks ``(n, H, W)``."""
    items = [frames] if isinstance(frames, np.ndarray) or is_torch(frames) else frames
    for x in items:
        if is_torch(x):
            x = x.detach().cpu().numpy()
        if not isinstance(x, np.ndarray) or x.dtype != np.uint16 or x.ndim not in (2, 3):
            raise InputError(f"{where}: depth-map frames must be uint16 (H, W) or (T, H, W) codes, got "
                             f"{getattr(x, 'dtype', type(x).__name__)} {getattr(x, 'shape', '')}")
        if x.size and x.max() > QMAX:
            raise InputError(f"{where}: depth-map codes must be 0..{QMAX}, got {x.max()}")
        yield x[None] if x.ndim == 2 else x



# ------------------------------------------------------------------------------ encoding
@contextmanager
def quiet_libav():
    """FFmpeg's log through PyAV at ERROR while we encode (x264 prints its statistics at INFO);
    the previous level is restored. Every :class:`VideoWriter` call runs inside it, since LeRobot
    (``get_video_info``) puts FFmpeg's own callback back, which prints at INFO to fd 2."""
    import av.logging

    previous = av.logging.get_level()
    av.logging.set_level(av.logging.ERROR)
    try:
        yield
    finally:
        av.logging.set_level(previous)


class VideoWriter:
    """One mp4 being written: a continuous encoder session fed frame batches ``(n, H, W, 3)``
    uint8 RGB (or, for a LeRobot depth map, ``(n, H, W)`` uint16 codes: ``frame_format``
    ``gray12le``). ``style``: ``"imac"`` (frame ``i`` at ``pts = i / fps``, ``faststart``) or
    ``"lerobot"`` (LeRobot 0.4.4's ``encode_video_frames`` call for call)."""

    def __init__(self, path: Path, encoding: VideoEncoding, fps: int, height: int, width: int, *,
                 style: str = "imac", frame_format: str = "rgb24"):
        import av

        if style not in ("imac", "lerobot"):
            raise InputError(f"VideoWriter style must be 'imac' or 'lerobot', got {style!r}")
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        self.path, self.style, self.frame_format = path, style, frame_format
        if style == "lerobot":
            self.container = av.open(str(path), "w")
        else:
            self.container = av.open(str(path), mode="w", format="mp4", container_options={"movflags": "faststart"})
        try:
            if style == "lerobot":
                self.stream = self.container.add_stream(encoding.codec, fps, options=encoding.encoder_options())
                self.stream.pix_fmt = encoding.pix_fmt
                self.stream.width = width
                self.stream.height = height
            else:
                self.stream = self.container.add_stream(encoding.codec, rate=fps, options=encoding.encoder_options())
                self.stream.width = width
                self.stream.height = height
                self.stream.pix_fmt = encoding.pix_fmt
                self.stream.time_base = Fraction(1, fps)
        except Exception:
            self.container.close()
            raise
        self.time_base = Fraction(1, fps)
        self.hw = (height, width)
        self.frames = 0
        self.bytes = 0

    def write(self, batch: np.ndarray) -> None:
        import av

        with quiet_libav(), scheduling_kept():  # the encoder opens at the first frame
            for frame in batch:
                vf = av.VideoFrame.from_ndarray(np.ascontiguousarray(frame), format=self.frame_format)
                if self.style == "imac":
                    vf.pts = self.frames
                    vf.time_base = self.time_base
                self._mux(self.stream.encode(vf))
                self.frames += 1

    def _mux(self, packets) -> None:
        for packet in packets:
            self.bytes += packet.size
            self.container.mux(packet)

    def close(self) -> None:
        with quiet_libav(), scheduling_kept():  # x264 prints its statistics as the encoder closes
            try:
                self._mux(self.stream.encode(None))
            finally:
                self.container.close()

    def abort(self) -> None:
        """Close without ending the stream (the caller deletes the file). The encoder is freed
        here, quietly: SVT-AV1 reports one freed mid-stream ("deinit called without sending
        EOS!") on fd 2, which after Ctrl-C would stand above the command's one line."""
        with quiet_libav(), native_stderr_silenced(), scheduling_kept():
            try:
                self.container.close()
            except Exception:  # noqa: BLE001 - already failing; the file is deleted anyway
                pass
            self.stream = None  # the last reference: the encoder is freed now, inside the silence


def encode_video(path: str | Path, frames, *, fps: int, encoding: VideoEncoding | None = None) -> Path:
    """Encode ``frames`` (uint8 RGB ``(T, H, W, 3)`` or an iterable of frames / chunks)
    into a new mp4 at ``path`` with ``encoding`` (default :meth:`VideoEncoding.lossless_rgb`).
    For benchmarks and one-off files; datasets use :func:`add_video_streams`."""
    path = Path(path)
    encoding = encoding or VideoEncoding.lossless_rgb()
    writer = None
    try:
        for batch in frame_batches(frames, str(path)):
            if writer is None:
                writer = VideoWriter(path, encoding, int(fps), batch.shape[1], batch.shape[2])
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


# ------------------------------------------------------------------------------ statistics
class ImageStats:
    """LeRobot's per-episode statistics of an image/video feature, exact, in constant memory.

    ``values``: what each stored level means, default the 256 pixel values of 3 RGB channels;
    for a LeRobot depth map the metres of the 4096 codes (one channel, not divided by 255).

    LeRobot (``compute_episode_stats``) samples the frames at ``sample_indices(length)``,
    downsamples each with ``auto_downsample_height_width`` and runs ``get_feature_stats``
    over their pixels per channel: min, max, mean, std (from the mean of squares), count
    (= sampled frames) and the q01..q99 of a 5000-bin histogram between min and max. Pixel
    values are integers 0..255, so all of that follows exactly from each channel's 256 value
    counts: sums of integers are exact in float64 whatever their order, and binning the 256
    values with their counts as weights is the same histogram. :meth:`stats` returns what
    ``get_feature_stats(samples.astype(float64), axis=(0, 2, 3), keepdims=True)`` returns
    (0..255 units, arrays of shape (1, 3, 1, 1)); :meth:`normalised` LeRobot's stored form
    (divided by 255, shape (3, 1, 1)). ``tests/test_dataset.py`` checks it against LeRobot.
    """

    def __init__(self, length: int, values: np.ndarray | None = None):
        self.length = int(length)
        self.wanted = set(lr.sample_indices(self.length)) if self.length > 0 else set()
        self.rgb = values is None
        self.values = np.arange(256, dtype=np.float64) if values is None else np.asarray(values, np.float64)
        self.channels = 3 if self.rgb else 1
        self.counts = np.zeros((self.channels, len(self.values)), dtype=np.int64)
        self.samples = 0
        self.seen = 0

    def update(self, batch: np.ndarray) -> None:
        """The next frames ``(n, H, W, 3)`` uint8 (depth map: ``(n, H, W)`` codes) of the episode, in order."""
        for i in range(len(batch)):
            if self.seen + i in self.wanted:
                frame = batch[i].transpose(2, 0, 1) if self.rgb else batch[i][None]
                img = lr.auto_downsample_height_width(frame)  # (C, h, w), as LeRobot
                for c in range(self.channels):
                    self.counts[c] += np.bincount(img[c].reshape(-1), minlength=len(self.values))
                self.samples += 1
        self.seen += len(batch)

    def stats(self) -> dict[str, np.ndarray]:
        quantile_list = lr.DEFAULT_QUANTILES
        if self.seen != self.length:
            raise InputError(f"image stats: {self.seen} frames seen, the episode has {self.length}")
        values = self.values
        n = self.counts.sum(axis=1)[0]
        out = {k: [] for k in ("min", "max", "mean", "std")}
        quantiles = [[] for _ in quantile_list]
        for c in range(self.channels):
            cnt = self.counts[c]
            present = np.flatnonzero(cnt)
            lo, hi = values[present[0]], values[present[-1]]
            mean = (values * cnt).sum() / n
            mean_sq = (values * values * cnt).sum() / n
            out["min"].append(lo)
            out["max"].append(hi)
            out["mean"].append(mean)
            out["std"].append(np.sqrt(np.maximum(0, mean_sq - mean ** 2)))
            # LeRobot's histogram quantiles over the same bins (RunningQuantileStats)
            rq = lr.RunningQuantileStats()
            edges = np.linspace(lo - 1e-10, hi + 1e-10, rq._num_quantile_bins + 1)
            hist, _ = np.histogram(values[present], bins=edges, weights=cnt[present].astype(np.float64))
            for k, q in enumerate(quantile_list):
                quantiles[k].append(rq._compute_single_quantile(hist, edges, q * n))
        stats = {k: np.asarray(v, dtype=np.float64).reshape(1, self.channels, 1, 1) for k, v in out.items()}
        stats["count"] = np.array([self.samples])
        for k, q in enumerate(quantile_list):
            stats[f"q{int(q * 100):02d}"] = np.asarray(quantiles[k], dtype=np.float64).reshape(1, self.channels, 1, 1)
        order = ("min", "max", "mean", "std", "count", *(f"q{int(q * 100):02d}" for q in quantile_list))
        return {k: stats[k] for k in order}

    def normalised(self) -> dict[str, np.ndarray]:
        """As stored in ``meta/episodes`` and ``stats.json``: RGB /255, shape (3, 1, 1); a depth
        map in metres, shape (1, 1, 1) (LeRobot 0.6 does not divide depth); ``count`` as is."""
        scale = 255.0 if self.rgb else 1.0
        return {k: v if k == "count" else np.squeeze(v / scale, axis=0) for k, v in self.stats().items()}
