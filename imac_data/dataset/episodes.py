"""A new LeRobot dataset written episode by episode, frames as they come.

:class:`EpisodeWriter` is LeRobot 0.4.4's own writer (``LeRobotDataset.create``,
``add_frame``, ``save_episode``, ``finalize``: its parquet files, metadata, stats and video
file layout) with one part replaced: the video encoder. LeRobot's default path saves every
camera frame as a PNG and encodes the PNGs per episode; its ``streaming_encoding`` option
drops each episode's last frame in 0.4.4. Here each frame is encoded the moment it arrives
(:class:`_FrameEncoder`, plugged into LeRobot's streaming-encoder slot), with LeRobot's own
settings (:meth:`VideoEncoding.lerobot_default`: libsvtav1, yuv420p, crf 30, gop 2, preset
12) and LeRobot's own container calls, so the mp4 files are byte-identical to the PNG
path's, without the PNGs; the image stats are LeRobot's, computed exactly in constant
memory (:class:`~imac_data.dataset.videos.ImageStats`; with a correct ``std``, which
LeRobot's uint8 arithmetic overflows). Memory: the episode's tabular rows (a few hundred
bytes per frame) and the encoders' buffers.
"""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from imac_data import lerobot_compat as lr
from imac_data.console import scheduling_kept
from imac_data.dataset.files import write_parquet_atomic
from imac_data.dataset.videos import ImageStats, VideoEncoding, VideoWriter
from imac_data.errors import InputError
from imac_data.layout import STATS_COLUMNS, episodes_dir

__all__ = ["EpisodeWriter"]


class _FrameEncoder:
    """LeRobot 0.4.4's streaming-encoder interface (``start_episode``, ``feed_frame``,
    ``finish_episode``, ``cancel_episode``, ``close``), served synchronously by our writer:
    nothing is queued, nothing dropped."""

    def __init__(self, fps: int, encoding: VideoEncoding):
        self.fps, self.encoding = fps, encoding
        self.length: int | None = None  # frames of the coming episode (for the stats' sampling)
        self._writers: dict[str, VideoWriter] = {}
        self._stats: dict[str, ImageStats] = {}
        self._dirs: dict[str, Path] = {}
        self._temp_dir: Path | None = None

    def start_episode(self, video_keys: list[str], temp_dir: Path, depth_video_keys=None) -> None:
        if depth_video_keys:  # LeRobot >= 0.6 passes its depth-map keys; these writers take RGB only
            raise InputError(f"EpisodeWriter: depth-map video features {list(depth_video_keys)} are not written here")
        if self._writers:
            self.cancel_episode()
        if self.length is None:
            raise RuntimeError("EpisodeWriter: the episode length must be set before its first frame")
        self._temp_dir = Path(temp_dir)
        self._keys = list(video_keys)
        self._stats = {k: ImageStats(self.length) for k in self._keys}

    def feed_frame(self, video_key: str, image: np.ndarray) -> None:
        frame = np.asarray(image)
        if frame.ndim != 3 or frame.shape[-1] != 3 or frame.dtype != np.uint8:
            raise InputError(f"{video_key}: frames must be (H, W, 3) uint8 RGB, got {frame.shape} {frame.dtype}")
        w = self._writers.get(video_key)
        if w is None:
            d = Path(tempfile.mkdtemp(dir=self._temp_dir))  # LeRobot removes the file's directory after moving it
            self._dirs[video_key] = d
            w = self._writers[video_key] = VideoWriter(d / f"{video_key}.mp4", self.encoding, self.fps,
                                                       frame.shape[0], frame.shape[1], style="lerobot")
        w.write(frame[None])
        self._stats[video_key].update(frame[None])

    def finish_episode(self) -> dict[str, tuple[Path, dict]]:
        out = {}
        for key in self._keys:
            w = self._writers.pop(key)
            w.close()
            out[key] = (w.path, self._stats[key].stats())
        self._dirs.clear()
        self.length = None
        return out

    def cancel_episode(self) -> None:
        for w in self._writers.values():
            w.abort()
        for d in self._dirs.values():
            shutil.rmtree(d, ignore_errors=True)
        self._writers.clear()
        self._dirs.clear()
        self.length = None

    def close(self) -> None:
        self.cancel_episode()


class EpisodeWriter:
    """A new LeRobot v3.0 dataset at ``root`` (must not exist) with ``features`` (LeRobot's
    feature dicts; ``video`` features are encoded with ``encoding``)::

        writer = EpisodeWriter(root, "local/x", fps=25, features=features)
        writer.begin_episode(T, task="...")
        writer.add_frames({"observation.state": (n, D) array, "observation.images.cam": (n, H, W, 3), ...})
        ...
        writer.end_episode()
        writer.finish()     # or writer.abort() on error

    ``threads``: encoder threads (SVT-AV1's output does not depend on them).
    """

    def __init__(self, root: str | Path, repo_id: str, *, fps: int, features: Mapping[str, dict],
                 robot_type: str | None = None, encoding: VideoEncoding | None = None, threads: int | None = None):
        encoding = encoding or VideoEncoding.lerobot_default()
        if threads is not None:
            encoding = encoding.with_threads(threads)
        self.root = Path(root)
        self.dataset = lr.create_dataset(repo_id, fps=int(fps), features=dict(features), root=self.root,
                                         robot_type=robot_type, encoding=encoding)
        self.encoder = _FrameEncoder(int(fps), encoding)
        lr.set_streaming_encoder(self.dataset, self.encoder)  # LeRobot routes video frames here (add_frame)
        self.video_keys = [k for k, f in features.items() if f["dtype"] == "video"]
        self._length: int | None = None
        self._n = 0
        self._task = ""

    def begin_episode(self, length: int, task: str) -> None:
        if self._length is not None:
            raise RuntimeError("begin_episode() while an episode is open")
        if length < 1:
            raise InputError(f"an episode needs at least one frame, got {length}")
        self._length, self._n, self._task = int(length), 0, task
        self.encoder.length = int(length)

    def add_frames(self, rows: Mapping[str, np.ndarray | Sequence]) -> None:
        """The next ``n`` frames: ``{feature: (n, ...)}`` for every feature of the dataset."""
        if self._length is None:
            raise RuntimeError("add_frames() outside an episode")
        n = {len(v) for v in rows.values()}
        if len(n) != 1:
            raise InputError(f"add_frames: features have different frame counts {sorted(n)}")
        n = n.pop()
        if self._n + n > self._length:
            raise InputError(f"add_frames: more frames than the episode's {self._length}")
        for i in range(n):
            frame = {k: v[i] for k, v in rows.items()}
            frame["task"] = self._task
            self.dataset.add_frame(frame)
        self._n += n

    def end_episode(self) -> None:
        if self._n != self._length:
            raise InputError(f"episode has {self._n} frames, expected {self._length}")
        with scheduling_kept():  # LeRobot encodes its cameras here (SVT-AV1 leaves a root caller real-time)
            self.dataset.save_episode()
        self._length = None

    def finish(self) -> None:
        with scheduling_kept():
            self.dataset.finalize()
        self._stats_in_feature_order()

    def _stats_in_feature_order(self) -> None:
        """LeRobot's streaming slot puts the video features' episode stats after all others
        in ``meta/episodes``; its PNG path (and so every dataset LeRobot writes by default)
        has them in feature order. Put them there, so the files match LeRobot's own."""
        import pyarrow.parquet as pq

        order = {k: i for i, k in enumerate(self.dataset.meta.features)}
        for f in sorted(episodes_dir(self.root).rglob("*.parquet")):
            table = pq.read_table(f)
            names = table.column_names
            stats = [n for n in names if n.startswith(STATS_COLUMNS)]
            if not stats:
                continue
            first = names.index(stats[0])
            ranked = sorted(stats, key=lambda n: (order.get(n.split("/")[1], len(order)), stats.index(n)))
            new = names[:first] + ranked + [n for n in names[first:] if n not in stats]
            if new != names:
                write_parquet_atomic(table.select(new), f)

    def abort(self) -> None:
        """Stop LeRobot's writers and our encoders, so nothing writes into ``root`` after the
        caller removes it."""
        try:
            self.encoder.cancel_episode()
        finally:
            lr.close_writers(self.dataset)
