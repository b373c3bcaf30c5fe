"""One episode of a LeRobot v3.0 dataset, read frame range by frame range.

:class:`LeRobotEpisodeReader` has the interface the streamed pipeline reads
(:meth:`imac_data.augment.pipeline.EpisodePipeline.chunks`; the HDF5 one is
:class:`imac_data.sources.hdf5.EpisodeReader`): ``qpos`` and ``action`` (``T x D`` floats,
read once), ``images(cam, lo, hi)`` and ``depth_mm(cam, lo, hi)``. The camera videos are
decoded with PyAV as one sequential pass per camera: the decoder is opened at the
episode's start in its video file and each call takes the next frames, so memory holds
one frame range, whatever the episode's length. A frame is matched to its index by its
timestamp (``from_timestamp + index / fps``, as LeRobot's loader does).

Recorded depth of the source (``depth.feature`` with ``{cam}``) is read in the recipe's
``depth.format``: ``millimetres`` or ``metres`` for a per-frame array or image feature in
the data files, ``codec`` for a video in our colour codec (decoded with the recipe's
``depth.codec`` preset), or ``lerobot`` for LeRobot's native depth map (12-bit ``gray12le``
codes, :mod:`imac_data.core.depth_map`); without a format, a feature flagged as a depth map
is read as ``lerobot`` and an array as ``millimetres``. It is returned in millimetres for
:class:`~imac_data.sources.depth.RecordedDepth`.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import av
import numpy as np

from imac_data.core.depth import DepthCodec
from imac_data.core.depth_map import PIX_FMT, DepthMapParams, depth_marker, params_of_feature
from imac_data.errors import InputError
from imac_data.layout import video_column

__all__ = ["LeRobotEpisodeReader", "DepthFeature"]


class DepthFeature:
    """A source dataset's recorded depth: feature ``pattern`` (``{cam}`` = camera name) in
    ``format`` (millimetres | metres | codec | lerobot, or None: from the feature;
    ``codec``: the DepthCodec preset). :meth:`check` settles the format and, for LeRobot's
    depth maps, each camera's quantiser (:attr:`params`)."""

    def __init__(self, pattern: str, format: str | None, codec: str = "manipulation"):
        self.pattern, self.format = pattern, format
        self.codec = DepthCodec.preset(codec) if format == "codec" else None
        self.params: dict[str, DepthMapParams] = {}
        self.src = None  # the dataset the feature was checked in: depth is read from it

    def key(self, cam: str) -> str:
        return self.pattern.replace("{cam}", cam)

    def check(self, src, cameras: list[str], where: str) -> None:
        """Everything about the feature that can be checked from ``info.json``, before any work."""
        self.src = src
        formats = {}
        for cam in cameras:
            key = self.key(cam)
            if key not in src.features:
                raise InputError(f"{where}: depth.feature: dataset {src.root} has no feature {key!r} for camera "
                                 f"{cam!r}")
            feature, at = src.features[key], f"dataset {src.root}: feature {key!r}"
            try:
                marked = bool(depth_marker(feature))
            except ValueError as e:
                raise InputError(f"{where}: depth.feature: {at}: {e}") from None
            dtype = feature["dtype"]
            fmt = self.format or ("lerobot" if marked else "millimetres")
            if marked and fmt != "lerobot":
                raise InputError(f"{where}: depth.format {fmt!r}, but {at} is a LeRobot depth map (info.is_depth_map): "
                                 "set depth.format: lerobot or leave it out")
            if fmt == "lerobot":
                self.params[cam] = params_of_feature(feature, f"{where}: depth.feature: {at}")
            elif self.format is None and dtype == "video":
                raise InputError(f"{where}: {at} is a video that is not flagged as a LeRobot depth map; if it holds "
                                 "our colour codec, set depth.format: codec")
            elif (fmt == "codec") != (dtype == "video"):
                raise InputError(f"{where}: depth.format {fmt!r} does not fit {at} (dtype {dtype}): the codec is a "
                                 "video, millimetres/metres are arrays or images")
            formats[cam] = fmt
        if len(set(formats.values())) > 1:
            raise InputError(f"{where}: depth.feature: the cameras' depth features have different formats {formats}")
        self.format = next(iter(formats.values()), self.format)

    @property
    def is_video(self) -> bool:
        return self.format in ("codec", "lerobot")

    def check_streams(self, src, cameras: list[str], where: str) -> None:
        """LeRobot depth maps: every video file of the feature really holds ``gray12le`` frames
        (12-bit codes; anything else would decode to other numbers)."""
        if self.format != "lerobot":
            return
        for cam in cameras:
            key = self.key(cam)
            for path in sorted({src.video_file(key, row) for row in src.episodes}):
                got = stream_pix_fmt(path)
                if got != PIX_FMT:
                    raise InputError(f"{where}: depth.feature: dataset {src.root}: {path} ({key}) is {got}, not "
                                     f"{PIX_FMT}: it does not hold LeRobot depth-map codes")


class _VideoFrames:
    """Sequential frames ``0..T-1`` of one episode in one video file (PyAV)."""

    def __init__(self, path: Path, start_s: float, fps: float, length: int, where: str, pix_fmt: str = "rgb24"):
        self.path, self.start_s, self.fps, self.length, self.where = path, start_s, fps, length, where
        self.pix_fmt = pix_fmt  # rgb24: (H, W, 3) uint8; gray12le: (H, W) uint16 codes
        self._iter: Iterator[tuple[int, np.ndarray]] | None = None
        self._next = 0  # index of the next frame the iterator yields
        self._container = None

    def _frames(self) -> Iterator[tuple[int, np.ndarray]]:
        if not self.path.is_file():
            raise InputError(f"{self.where}: video file {self.path} is missing")
        self._container = container = av.open(str(self.path))
        stream = container.streams.video[0]
        stream.thread_type = "AUTO"
        if self.pix_fmt == PIX_FMT and stream.codec_context.pix_fmt != PIX_FMT:
            raise InputError(f"{self.where}: {self.path} is {stream.codec_context.pix_fmt}, not {PIX_FMT}")
        container.seek(int(self.start_s / stream.time_base), stream=stream, backward=True, any_frame=False)
        tol = 0.5 / self.fps
        for frame in container.decode(stream):
            index = int(round((float(frame.pts * stream.time_base) - self.start_s) * self.fps))
            if index < 0 or abs(float(frame.pts * stream.time_base) - self.start_s - index / self.fps) > tol:
                continue
            if index >= self.length:
                break
            yield index, frame.to_ndarray(format=self.pix_fmt)

    def read(self, lo: int, hi: int) -> np.ndarray:
        if self._iter is None or lo < self._next:
            self.close()
            self._iter, self._next = self._frames(), 0
        out = []
        for index, rgb in self._iter:
            if index < self._next:
                continue
            if index != self._next:
                raise InputError(f"{self.where}: frame {self._next} is missing in {self.path} (next decoded: {index})")
            self._next = index + 1
            if index >= lo:
                out.append(rgb)
            if self._next >= hi:
                break
        if len(out) != hi - lo:
            raise InputError(f"{self.where}: {self.path} holds frames up to {self._next - 1} of this episode, "
                             f"frames {lo}:{hi} were asked for")
        return np.stack(out)

    def close(self) -> None:
        if self._container is not None:
            self._container.close()
            self._container = None
        self._iter = None


class LeRobotEpisodeReader:
    """Episode ``row["episode_index"]`` of the :class:`~imac_data.sources.lerobot_dataset.SourceDataset`
    ``src`` for the pipeline. ``cameras``: camera name -> video feature key; ``state`` and
    ``action``: its ``(T, D)`` joint vectors; ``depth``: a :class:`DepthFeature` or None."""

    def __init__(self, src, row: dict, cameras: dict[str, str], state: np.ndarray, action: np.ndarray,
                 depth: DepthFeature | None = None):
        self.src, self.row, self.index = src, row, int(row["episode_index"])
        self.path = f"{src.root} episode {self.index}"
        self.qpos, self.action = np.asarray(state, np.float64), np.asarray(action, np.float64)
        self.qvel = None
        self.camera_keys = dict(cameras)
        self.cameras = sorted(cameras)
        self.image_hw = {c: src.image_hw(k) for c, k in cameras.items()}
        self.depth = depth
        self._videos: dict[str, _VideoFrames] = {}

    @property
    def num_frames(self) -> int:
        return int(self.row["length"])

    def __enter__(self) -> LeRobotEpisodeReader:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        for v in self._videos.values():
            v.close()
        self._videos.clear()

    def _video(self, key: str, pix_fmt: str = "rgb24", src=None) -> _VideoFrames:
        if key not in self._videos:
            src = src or self.src
            r, info = src.episodes[self.index], src.info
            path = src.video_file(key, r)
            self._videos[key] = _VideoFrames(path, float(r[video_column(key, "from_timestamp")]), float(info["fps"]),
                                             self.num_frames, f"{self.path} {key}", pix_fmt)
        return self._videos[key]

    def images(self, cam: str, start: int, stop: int) -> np.ndarray:
        """RGB frames ``start:stop`` of camera ``cam``, ``(n, H, W, 3)`` uint8."""
        if cam not in self.camera_keys:
            raise InputError(f"{self.path}: no camera {cam!r} (has {self.cameras})")
        frames = self._video(self.camera_keys[cam]).read(start, stop)
        if frames.shape[1:3] != self.image_hw[cam]:
            raise InputError(f"{self.path}: {self.camera_keys[cam]} frames are {frames.shape[1:3]}, its feature says "
                             f"{self.image_hw[cam]}")
        return frames

    def depth_mm(self, cam: str, start: int, stop: int) -> np.ndarray | None:
        """Recorded depth frames ``start:stop`` of ``cam`` in millimetres, or None without a
        depth feature."""
        if self.depth is None:
            return None
        key = self.depth.key(cam)
        src = self.depth.src or self.src  # the source's own depth: a copy may have dropped the feature
        if self.depth.format == "lerobot":
            codes = self._video(key, PIX_FMT, src).read(start, stop)
            return self.depth.params[cam].dequantize(codes) * np.float32(1000.0)
        if self.depth.format == "codec":
            rgb = self._video(key, "rgb24", src).read(start, stop)
            return np.asarray(self.depth.codec.decode(rgb, channel_axis=-1), dtype=np.float32) * 1000.0
        values = self._array_rows(src, key, start, stop)
        return values * 1000.0 if self.depth.format == "metres" else values

    def _array_rows(self, src, key: str, start: int, stop: int) -> np.ndarray:
        """Frames ``start:stop`` of an array or image feature from the episode's data file in ``src``."""
        import pyarrow.parquet as pq

        path = src.data_file(src.episodes[self.index])
        table = pq.read_table(path, columns=["frame_index", key],
                              filters=[("episode_index", "=", self.index), ("frame_index", ">=", start),
                                       ("frame_index", "<", stop)])
        order = np.argsort(table.column("frame_index").to_numpy())
        column = table.column(key).to_pylist()
        if len(column) != stop - start:
            raise InputError(f"{self.path}: {key!r} has {len(column)} rows for frames {start}:{stop}")
        if src.features[key]["dtype"] == "image":
            import cv2

            frames = [cv2.imdecode(np.frombuffer(column[i]["bytes"], np.uint8), cv2.IMREAD_UNCHANGED) for i in order]
            if any(f is None or f.ndim != 2 for f in frames):
                raise InputError(f"{self.path}: {key!r} holds images that are not single-channel depth")
            return np.stack(frames).astype(np.float32)
        values = np.asarray([column[i] for i in order], dtype=np.float32)
        if values.ndim == 4 and values.shape[1] == 1:
            values = values[:, 0]
        elif values.ndim == 4 and values.shape[-1] == 1:
            values = values[..., 0]
        if values.ndim != 3:
            raise InputError(f"{self.path}: {key!r} must be (H, W) depth per frame, got {values.shape[1:]}")
        return values


def stream_pix_fmt(path: str | Path) -> str | None:
    """The pixel format of the first video stream of ``path`` (None: unreadable)."""
    try:
        with av.open(str(path)) as container:
            return container.streams.video[0].codec_context.pix_fmt
    except Exception:  # noqa: BLE001 - any demuxer error: the file is not what it should be
        return None


def count_decodable_frames(path: str | Path) -> tuple[int, str | None]:
    """How many frames of the first video stream of ``path`` decode, and the decoder's error
    that stopped it (``None``: the whole file decoded). One decoder thread: callers check
    several files at once."""
    n = 0
    try:
        with av.open(str(path)) as container:
            stream = container.streams.video[0]
            stream.thread_count = 1
            for _ in container.decode(stream):
                n += 1
    except Exception as e:  # noqa: BLE001 - any demuxer or decoder error is the finding
        return n, f"{type(e).__name__}: {e}"
    return n, None
