"""ALOHA / AgileX Cobot Magic HDF5 episodes: the raw format we read (and our simulator writes).

One file per episode (``episode_0.hdf5``, ``episode_1.hdf5``, ...)::

    /observations/qpos                 (T, D) float   measured joint state
    /observations/qvel                 (T, D) float   optional
    /observations/images/<cam>         (T, H, W, 3) uint8 RGB
                                       or (T, L) uint8 padded JPEG bytes when compressed
    /observations/images_depth/<cam>   (T, h, w) uint16 (AgileX) or float millimetres, optional;
                                       the images' aspect ratio (resized to them)
    /observations/segmentation/<cam>   (T, H, W) int16 MuJoCo geom id, -1 = none (simulator only)
    /action                            (T, D) float   commanded joint targets
    /compress_len                      (n_cams, T)    JPEG byte counts, rows in sorted camera order
    attrs: sim, compress, and optionally fps, task, source, policy_name, checkpoint, success,
           sim_task and sim_seed (a simulated episode's task and start seed: reset(sim_seed)
           and the recorded actions re-simulate it), segmentation_labels (JSON {geom id:
           [geom name, body name]})

The compressed variant stores what ``cv2.imencode('.jpg', rgb)`` returns for the RGB
array (the ALOHA/ACT recorders pass RGB straight to OpenCV), so decoding returns RGB
without a channel swap.

Reading validates everything a build relies on and raises :class:`InputError`
naming the file and the key.
"""

from __future__ import annotations

import contextlib
import json
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import h5py
import numpy as np

from imac_data.core.cameras import Camera, same_aspect
from imac_data.core.robot.model import RobotModel
from imac_data.errors import InputError

SOURCES = ("teleop", "policy")


@dataclass
class EpisodeInfo:
    """Episode-level metadata (what produced the episode, and how it ended)."""

    task: str | None = None
    source: str | None = None  # "teleop" | "policy"
    policy_name: str | None = None
    checkpoint: str | None = None
    success: bool | None = None
    sim_task: str | None = None  # a simulated episode's task (imac_data.sources.sim.tasks.TASKS)
    sim_seed: int | None = None  # and its start seed: gym-aloha's reset(seed)
    sim_settle_s: float | None = None  # and the physics run before its first frame (SimEnv's settle_s)

    def __post_init__(self) -> None:
        if self.source is not None and self.source not in SOURCES:
            raise InputError(f"episode source must be one of {SOURCES}, got {self.source!r}")


def parse_success(value, where: str) -> bool | None:
    """An episode's success flag from metadata: a boolean, 1/0, or true/false, yes/no,
    success/failure text (any case); None when absent or empty. Anything else is refused
    (``bool("no")`` would read as a success)."""
    if isinstance(value, bytes):
        value = value.decode(errors="replace")
    if value is None or (isinstance(value, str) and not value.strip()):
        return None
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    text = str(value).strip().lower()
    if text in ("1", "true", "yes", "success"):
        return True
    if text in ("0", "false", "no", "failure", "fail"):
        return False
    raise InputError(f"{where}: success must be true/false (or 1/0), got {value!r}")


def episode_attributes(f: h5py.File, path: Path) -> tuple[EpisodeInfo, float | None]:
    """The episode's metadata attributes and its recorded rate (``fps``, or None), checked,
    with errors naming the file and the attribute."""
    attrs = f.attrs
    where = f"{path}: attribute"
    success = parse_success(attrs.get("success"), f"{where} 'success'")
    seed = attrs.get("sim_seed")
    if seed is not None:
        if isinstance(seed, (bool, np.bool_)) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise InputError(f"{where} 'sim_seed' must be a non-negative integer, got {seed!r}")
        seed = int(seed)
    settle = attrs.get("sim_settle_s")
    if settle is not None:
        if isinstance(settle, (bool, np.bool_)) or not isinstance(settle, (int, float, np.integer, np.floating)) \
                or not 0.0 <= float(settle) < float("inf"):
            raise InputError(f"{where} 'sim_settle_s' must be a non-negative number of seconds, got {settle!r}")
        settle = float(settle)
    try:
        info = EpisodeInfo(task=_str_attr(attrs.get("task")), source=_str_attr(attrs.get("source")),
                           policy_name=_str_attr(attrs.get("policy_name")),
                           checkpoint=_str_attr(attrs.get("checkpoint")), success=success,
                           sim_task=_str_attr(attrs.get("sim_task")), sim_seed=seed, sim_settle_s=settle)
    except InputError as e:  # EpisodeInfo checks its fields; say which file
        raise InputError(f"{where} 'source': {e}") from None
    fps = None
    if "fps" in attrs:
        try:
            fps = float(attrs["fps"])
        except (TypeError, ValueError):
            raise InputError(f"{where} 'fps' must be a number, got {attrs['fps']!r}") from None
        if not (math.isfinite(fps) and fps > 0):
            raise InputError(f"{where} 'fps' must be a positive number, got {fps}")
    return info, fps


@dataclass
class RawEpisode:
    qpos: np.ndarray  # (T, D)
    action: np.ndarray  # (T, D)
    images: dict[str, np.ndarray]  # cam -> (T, H, W, 3) uint8
    qvel: np.ndarray | None = None
    depth_mm: dict[str, np.ndarray] = field(default_factory=dict)  # cam -> (T, H, W) uint16
    segmentation: dict[str, np.ndarray] = field(default_factory=dict)  # cam -> (T, H, W) int16
    segmentation_labels: dict[int, tuple[str, str]] = field(default_factory=dict)
    info: EpisodeInfo = field(default_factory=EpisodeInfo)
    fps: float | None = None

    @property
    def num_frames(self) -> int:
        return int(self.qpos.shape[0])

    @property
    def cameras(self) -> list[str]:
        return sorted(self.images)


def episode_paths(source_dir: str | Path) -> list[Path]:
    """The ``*.hdf5`` episode files of a directory in natural order (episode_2 before episode_10)."""
    source_dir = Path(source_dir)
    if not source_dir.is_dir():
        raise InputError(f"source directory does not exist: {source_dir}")
    paths = [p for p in source_dir.iterdir() if p.suffix in (".hdf5", ".h5") and p.is_file()]
    if not paths:
        raise InputError(f"no .hdf5 episodes in {source_dir}")

    def natural(p: Path):
        return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", p.name)]

    return sorted(paths, key=natural)


# --------------------------------------------------------------------------- write


def write_episode(path: str | Path, episode: RawEpisode, *, compress: bool = False,
                  jpeg_quality: int = 95, sim: bool = True) -> None:
    """Write an episode in the ALOHA layout; atomic (temp file renamed into place)."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        _write_hdf5(tmp, episode, compress=compress, jpeg_quality=jpeg_quality, sim=sim)
        tmp.replace(path)
    finally:
        tmp.unlink(missing_ok=True)


def _write_hdf5(tmp: Path, episode: RawEpisode, *, compress: bool, jpeg_quality: int, sim: bool) -> None:
    cams = sorted(episode.images)
    T = episode.num_frames
    with h5py.File(tmp, "w") as f:
        f.attrs["sim"] = sim
        f.attrs["compress"] = compress
        if episode.fps is not None:
            f.attrs["fps"] = float(episode.fps)
        for key in ("task", "source", "policy_name", "checkpoint", "sim_task"):
            value = getattr(episode.info, key)
            if value is not None:
                f.attrs[key] = value
        if episode.info.success is not None:
            f.attrs["success"] = bool(episode.info.success)
        if episode.info.sim_seed is not None:
            f.attrs["sim_seed"] = np.int64(episode.info.sim_seed)
        if episode.info.sim_settle_s is not None:
            f.attrs["sim_settle_s"] = float(episode.info.sim_settle_s)
        obs = f.create_group("observations")
        obs.create_dataset("qpos", data=episode.qpos)
        if episode.qvel is not None:
            obs.create_dataset("qvel", data=episode.qvel)
        f.create_dataset("action", data=episode.action)
        images = obs.create_group("images")
        if compress:
            encoded = {
                cam: [cv2.imencode(".jpg", frame, [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality])[1].ravel()
                      for frame in episode.images[cam]]
                for cam in cams
            }
            lengths = np.array([[len(b) for b in encoded[cam]] for cam in cams], dtype=np.int64)
            width = int(lengths.max())
            for cam in cams:
                padded = np.zeros((T, width), dtype=np.uint8)
                for t, b in enumerate(encoded[cam]):
                    padded[t, : len(b)] = b
                images.create_dataset(cam, data=padded)
            f.create_dataset("compress_len", data=lengths)
        else:
            for cam in cams:
                images.create_dataset(cam, data=episode.images[cam], chunks=(1, *episode.images[cam].shape[1:]))
        if episode.depth_mm:
            depth = obs.create_group("images_depth")
            for cam, d in episode.depth_mm.items():
                depth.create_dataset(cam, data=d, chunks=(1, *d.shape[1:]), compression="gzip", compression_opts=1)
        if episode.segmentation:
            seg = obs.create_group("segmentation")
            for cam, s in episode.segmentation.items():
                seg.create_dataset(cam, data=s, chunks=(1, *s.shape[1:]), compression="gzip", compression_opts=1)
            f.attrs["segmentation_labels"] = json.dumps(
                {str(k): list(v) for k, v in episode.segmentation_labels.items()}
            )


# --------------------------------------------------------------------------- read


def _dataset(f: h5py.File, path: Path, key: str) -> h5py.Dataset:
    if key not in f:
        parent = key.rsplit("/", 1)[0] or "/"
        have = sorted(f[parent].keys()) if parent in f and isinstance(f[parent], h5py.Group) else []
        hint = f" (the file has {parent}: {have})" if have else ""
        raise InputError(f"{path}: missing HDF5 dataset '{key}'{hint}")
    obj = f[key]
    if not isinstance(obj, h5py.Dataset):
        raise InputError(f"{path}: '{key}' is a group, expected a dataset")
    return obj


def _joint_array(f: h5py.File, path: Path, key: str) -> np.ndarray:
    arr = _dataset(f, path, key)[()]
    if arr.ndim != 2 or not np.issubdtype(arr.dtype, np.number):
        raise InputError(f"{path}: '{key}' must be a (T, D) numeric array, got shape {arr.shape} {arr.dtype}")
    bad = ~np.isfinite(arr)
    if bad.any():
        t, j = np.argwhere(bad)[0]
        raise InputError(f"{path}: '{key}' has NaN/inf values (first at frame {t}, joint index {j})")
    return arr.astype(np.float64)


def _camera_names(f: h5py.File, path: Path) -> list[str]:
    if "observations/images" not in f or not isinstance(f["observations/images"], h5py.Group):
        raise InputError(f"{path}: missing HDF5 group '/observations/images'")
    cams = sorted(f["observations/images"].keys())
    if not cams:
        raise InputError(f"{path}: '/observations/images' holds no cameras")
    return cams


def _decode_jpeg_stack(data: np.ndarray, lengths: np.ndarray, path: Path, key: str, first: int = 0) -> np.ndarray:
    frames = []
    for t, n in enumerate(lengths):
        img = cv2.imdecode(data[t, : int(n)], cv2.IMREAD_COLOR)
        if img is None:
            raise InputError(f"{path}: '{key}' frame {first + t} is not a decodable JPEG")
        frames.append(img)
    if not frames:
        return np.zeros((0, 0, 0, 3), np.uint8)
    return np.stack(frames)


def probe_episode(path: str | Path) -> dict:
    """Cheap structural check of an episode without loading images: returns
    ``{"num_frames", "dof", "cameras", "image_hw", "compressed", "has_depth", "depth_cameras",
    "has_qvel", "fps", "info", "qpos_range"}`` (``qpos_range``: per-entry min and max) or raises
    InputError."""
    path = Path(path)
    try:
        f = h5py.File(path, "r")
    except OSError as e:
        raise InputError(f"{path}: not a readable HDF5 file ({e})") from None
    with f, damaged_hdf5(path):
        return _probe(f, path)


@contextlib.contextmanager
def damaged_hdf5(path: Path, what: str = ""):
    """HDF5's own errors while reading (a corrupt B-tree, object header or compressed chunk:
    h5py raises OSError, RuntimeError or KeyError) as an :class:`InputError` naming the file."""
    try:
        yield
    except (OSError, RuntimeError, KeyError) as e:
        raise InputError(f"{path}: damaged HDF5 file{what}: {type(e).__name__}: {e}") from None


def _probe(f: h5py.File, path: Path) -> dict:
    qpos = _joint_array(f, path, "observations/qpos")
    action = _joint_array(f, path, "action")
    T, D = qpos.shape
    if T == 0:
        raise InputError(f"{path}: the episode has no frames ('observations/qpos' is {qpos.shape})")
    if action.shape != (T, D):
        raise InputError(
            f"{path}: length/width mismatch: 'observations/qpos' is {qpos.shape}, 'action' is {action.shape}"
        )
    has_qvel = "observations/qvel" in f
    if has_qvel and _joint_array(f, path, "observations/qvel").shape != (T, D):
        raise InputError(f"{path}: 'observations/qvel' is {f['observations/qvel'].shape}, 'observations/qpos' is "
                         f"{qpos.shape}")
    info, fps = episode_attributes(f, path)
    cams = _camera_names(f, path)
    compressed = bool(f.attrs.get("compress", False))
    if compressed:
        lengths = _dataset(f, path, "compress_len")
        if lengths.shape != (len(cams), T):
            raise InputError(
                f"{path}: 'compress_len' has shape {lengths.shape}, expected ({len(cams)}, {T}) for cameras {cams}"
            )
    image_hw = {}
    for cam in cams:
        key = f"observations/images/{cam}"
        ds = f[key]
        if ds.shape[0] != T:
            raise InputError(f"{path}: '{key}' has {ds.shape[0]} frames, 'observations/qpos' has {T}")
        if not compressed:
            if ds.ndim != 4 or ds.shape[-1] != 3 or ds.dtype != np.uint8:
                raise InputError(f"{path}: '{key}' must be (T, H, W, 3) uint8, got {ds.shape} {ds.dtype}")
            image_hw[cam] = tuple(int(v) for v in ds.shape[1:3])
        else:  # the first frame's size: a later one of another size fails when it is read
            image_hw[cam] = tuple(_decode_jpeg_stack(ds[0:1], lengths[cams.index(cam), 0:1], path, key).shape[1:3])
    depth_cameras = sorted(f["observations/images_depth"].keys()) if "observations/images_depth" in f else []
    for cam in depth_cameras:
        if cam not in cams:
            raise InputError(f"{path}: 'observations/images_depth/{cam}' has no matching RGB camera in {cams}")
        _check_depth(f, path, cam, T, image_hw[cam])
    return {"num_frames": T, "dof": D, "cameras": cams, "compressed": compressed, "has_depth": bool(depth_cameras),
            "depth_cameras": depth_cameras, "has_qvel": has_qvel, "fps": fps, "info": info, "image_hw": image_hw,
            "qpos_range": (qpos.min(axis=0), qpos.max(axis=0))}


def check_episodes(paths: Sequence[Path], calibration: dict[str, Camera], robot: RobotModel) -> dict:
    """Validate every episode against each other, the calibration and the robot, without
    loading images (a compressed episode's first frames are decoded for their size).
    Returns the common probe (cameras, dof, image sizes) with ``total_frames`` and, over all
    episodes, ``qpos_range`` (per-entry min and max of the joint vector)."""
    if not paths:
        raise InputError("no episodes to ingest")
    first = probe_episode(paths[0])
    total, (lo, hi) = first["num_frames"], first["qpos_range"]
    for path in paths[1:]:
        probe = probe_episode(path)
        total += probe["num_frames"]
        if probe["cameras"] != first["cameras"]:
            raise InputError(
                f"episodes have different camera sets: {paths[0]} has {first['cameras']}, "
                f"{path} has {probe['cameras']}"
            )
        if probe["dof"] != first["dof"]:
            raise InputError(f"{path}: joint vector has {probe['dof']} entries, {paths[0]} has {first['dof']}")
        if probe["image_hw"] != first["image_hw"]:
            cam = next(c for c in first["cameras"] if probe["image_hw"][c] != first["image_hw"][c])
            raise InputError(f"{path}: 'observations/images/{cam}' is {probe['image_hw'][cam]} (HxW), "
                             f"{paths[0]} has {first['image_hw'][cam]}; every episode needs the same resolution")
        # one dataset has one feature set and one rate: what the first episode has, all must have
        if probe["depth_cameras"] != first["depth_cameras"]:
            raise InputError(f"{path}: recorded depth ('observations/images_depth') for cameras "
                             f"{probe['depth_cameras']}, {paths[0]} has it for {first['depth_cameras']}")
        if probe["has_qvel"] != first["has_qvel"]:
            has, lacks = (path, paths[0]) if probe["has_qvel"] else (paths[0], path)
            raise InputError(f"{has} has 'observations/qvel' and {lacks} has not; every episode needs the same keys")
        if probe["fps"] != first["fps"]:
            raise InputError(f"{path}: attribute 'fps' is {probe['fps']}, {paths[0]} has {first['fps']}; "
                             "one dataset has one frame rate")
        lo, hi = np.minimum(lo, probe["qpos_range"][0]), np.maximum(hi, probe["qpos_range"][1])
    cams = first["cameras"]
    extra = sorted(set(calibration) - set(cams))
    if extra:
        raise InputError(
            f"calibration has camera(s) {extra} that the episodes do not have (episodes have {cams})"
        )
    missing = sorted(set(cams) - set(calibration))
    if missing:
        raise InputError(f"episodes have camera(s) {missing} that the calibration does not describe")
    if first["dof"] != robot.dof:
        raise InputError(
            f"{paths[0]}: joint vector has {first['dof']} entries but robot {robot.config.name!r} "
            f"maps {robot.dof}"
        )
    for cam in calibration.values():
        if cam.link is not None and cam.link not in robot.link_names:
            raise InputError(f"camera {cam.name!r} is mounted on link {cam.link!r}, which the robot does not have")
        cam.for_images(*first["image_hw"][cam.name], where=f"the images of {paths[0]}")
    return {**first, "total_frames": total, "qpos_range": (lo, hi)}


DEPTH_DTYPES = "uint16 or float millimetres"


def _check_depth(f: h5py.File, path: Path, cam: str, T: int, image_hw: tuple[int, int]) -> h5py.Dataset:
    """The recorded depth of ``cam``: ``(T, h, w)`` uint16 or float millimetres, of the image's
    aspect ratio (a smaller or larger depth map is resized to the image, as K is)."""
    key = f"observations/images_depth/{cam}"
    d = _dataset(f, path, key)
    if d.ndim != 3 or not (d.dtype == np.uint16 or np.issubdtype(d.dtype, np.floating)):
        raise InputError(f"{path}: '{key}' must be (T, H, W) {DEPTH_DTYPES}, got {d.shape} {d.dtype}")
    if d.shape[0] != T:
        raise InputError(f"{path}: '{key}' has {d.shape[0]} frames, 'observations/qpos' has {T}")
    if not same_aspect(d.shape[1:3], image_hw):
        raise InputError(f"{path}: '{key}' is {d.shape[1]}x{d.shape[2]} (HxW), another aspect ratio than the "
                         f"{image_hw[0]}x{image_hw[1]} images of camera {cam!r}; depth must be registered to its "
                         "colour camera")
    return d


class EpisodeReader:
    """One episode opened for reading piece by piece: the joint vectors at once (``T x D``
    floats), images and depth by frame range, so memory follows the range, not the episode::

        with EpisodeReader(path) as ep:
            rgb = ep.images("cam_high", 0, 9)       # (9, H, W, 3) uint8 RGB
            mm = ep.depth_mm("cam_high", 0, 9)      # (9, h, w) uint16 millimetres, or None

    Opening validates the structure (:func:`probe_episode`); each range is checked as it
    is read (dtypes, decodable JPEGs) with an :class:`InputError` naming the file and key.
    """

    def __init__(self, path: str | Path, *, cameras: list[str] | None = None):
        self.path = Path(path)
        probe = probe_episode(self.path)
        self._file = h5py.File(self.path, "r")
        try:
            f = self._file
            all_cams = _camera_names(f, self.path)
            cams = list(all_cams if cameras is None else cameras)
            missing = [c for c in cams if c not in all_cams]
            if missing:
                raise InputError(f"{self.path}: camera(s) {missing} not in '/observations/images' (has {all_cams})")
            self._all_cams, self.cameras = all_cams, sorted(cams)
            self.compressed = probe["compressed"]
            self.qpos = _joint_array(f, self.path, "observations/qpos")
            self.action = _joint_array(f, self.path, "action")
            self.qvel = _joint_array(f, self.path, "observations/qvel") if "observations/qvel" in f else None
            self.info, self.fps = probe["info"], probe["fps"]
            self._lengths = f["compress_len"][()] if self.compressed else None
            self.image_hw = {c: probe["image_hw"][c] for c in self.cameras}
        except BaseException:
            self._file.close()
            raise

    def __enter__(self) -> EpisodeReader:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self._file.close()

    @property
    def num_frames(self) -> int:
        return int(self.qpos.shape[0])

    @property
    def depth_cameras(self) -> list[str]:
        group = self._file.get("observations/images_depth")
        return sorted(c for c in group.keys() if c in self.cameras) if group is not None else []

    def images(self, cam: str, start: int, stop: int) -> np.ndarray:
        """RGB frames ``start:stop`` of camera ``cam``, ``(n, H, W, 3)`` uint8."""
        key = f"observations/images/{cam}"
        if cam not in self._all_cams:
            raise InputError(f"{self.path}: no camera {cam!r} (has {self._all_cams})")
        with damaged_hdf5(self.path, f" ('{key}' frames {start}:{stop})"):
            data = self._file[key][start:stop]
        if self.compressed:
            lengths = self._lengths[self._all_cams.index(cam)][start:stop]
            frames = _decode_jpeg_stack(data, lengths, self.path, key, first=start)
            if hasattr(self, "image_hw") and frames.shape[1:3] != self.image_hw[cam]:
                raise InputError(f"{self.path}: '{key}' frames change size at {start}:{stop} "
                                 f"({frames.shape[1:3]} vs {self.image_hw[cam]})")
            return frames
        return data

    def depth_mm(self, cam: str, start: int, stop: int) -> np.ndarray | None:
        """Recorded depth frames ``start:stop`` of ``cam`` (``(n, h, w)`` uint16 or float millimetres),
        or None when the episode has none for that camera."""
        if f"observations/images_depth/{cam}" not in self._file:
            return None
        with damaged_hdf5(self.path, f" ('observations/images_depth/{cam}' frames {start}:{stop})"):
            return _check_depth(self._file, self.path, cam, self.num_frames, self.image_hw[cam])[start:stop]

    def segmentation(self, cam: str, start: int, stop: int) -> np.ndarray | None:
        key = f"observations/segmentation/{cam}"
        return self._file[key][start:stop] if key in self._file else None

    def segmentation_labels(self) -> dict[int, tuple[str, str]]:
        raw = json.loads(self._file.attrs.get("segmentation_labels", "{}"))
        return {int(k): tuple(v) for k, v in raw.items()}


def read_episode(path: str | Path, *, cameras: list[str] | None = None, load_depth: bool = True,
                 load_segmentation: bool = False) -> RawEpisode:
    """Load and validate one episode, all frames in memory (short episodes, tests, tools;
    the build reads chunk by chunk with :class:`EpisodeReader`)."""
    with EpisodeReader(path, cameras=cameras) as ep:
        T = ep.num_frames
        images = {cam: ep.images(cam, 0, T) for cam in ep.cameras}
        depth = {}
        if load_depth:
            for cam in ep.cameras:
                d = ep.depth_mm(cam, 0, T)
                if d is not None:
                    depth[cam] = d
        seg, labels = {}, {}
        if load_segmentation:
            for cam in ep.cameras:
                s = ep.segmentation(cam, 0, T)
                if s is not None:
                    seg[cam] = s
            labels = ep.segmentation_labels()
        return RawEpisode(qpos=ep.qpos, action=ep.action, qvel=ep.qvel, images=images, depth_mm=depth,
                          segmentation=seg, segmentation_labels=labels, info=ep.info, fps=ep.fps)


def _str_attr(value) -> str | None:
    if value is None:
        return None
    return value.decode() if isinstance(value, bytes) else str(value)


def tile_episode(src: str | Path, dst: str | Path, num_frames: int, *, chunk: int = 32) -> Path:
    """A long episode made from a recorded one, for memory and throughput benchmarks:
    ``num_frames`` frames of ``src`` played forward, backward, forward, ... (every frame,
    joint vector, action and depth map is a recorded one; the motion stays continuous).
    Written chunk by chunk (uncompressed RGB), so it needs no more memory than ``chunk``
    frames, whatever ``num_frames``; atomic (temp file renamed into place)."""
    src, dst = Path(src), Path(dst)
    if num_frames < 1:
        raise InputError(f"tile_episode: num_frames must be >= 1, got {num_frames}")
    tmp = dst.with_name(f".{dst.name}.tmp")
    try:
        with EpisodeReader(src) as ep, h5py.File(tmp, "w") as f:
            T = ep.num_frames
            period = max(2 * T - 2, 1)
            order = np.arange(num_frames) % period
            order = np.where(order < T, order, period - order)  # 0..T-1, T-2..1, 0..T-1, ...
            f.attrs["sim"] = True
            f.attrs["compress"] = False
            if ep.fps is not None:
                f.attrs["fps"] = ep.fps
            # not sim_task / sim_seed: the tiled motion is not what that start re-simulates to
            for key in ("task", "source", "policy_name", "checkpoint"):
                if getattr(ep.info, key) is not None:
                    f.attrs[key] = getattr(ep.info, key)
            obs = f.create_group("observations")
            obs.create_dataset("qpos", data=ep.qpos[order])
            if ep.qvel is not None:
                obs.create_dataset("qvel", data=ep.qvel[order])
            f.create_dataset("action", data=ep.action[order])
            images, depth = obs.create_group("images"), None
            for cam in ep.cameras:
                h, w = ep.image_hw[cam]
                out = images.create_dataset(cam, shape=(num_frames, h, w, 3), dtype=np.uint8, chunks=(1, h, w, 3))
                d = ep.depth_mm(cam, 0, 1)
                dout = None
                if d is not None:
                    depth = depth or obs.create_group("images_depth")
                    dout = depth.create_dataset(cam, shape=(num_frames, *d.shape[1:]), dtype=np.uint16,
                                                chunks=(1, *d.shape[1:]), compression="gzip", compression_opts=1)
                for lo in range(0, num_frames, chunk):
                    idx = order[lo:lo + chunk]
                    a, b = int(idx.min()), int(idx.max()) + 1  # read the span once, pick the frames
                    out[lo:lo + len(idx)] = ep.images(cam, a, b)[idx - a]
                    if dout is not None:
                        dout[lo:lo + len(idx)] = ep.depth_mm(cam, a, b)[idx - a]
        tmp.replace(dst)
    finally:
        tmp.unlink(missing_ok=True)
    return dst
