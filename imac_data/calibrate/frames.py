"""Which frames a camera is refined on, and where the robot's pixels in them come from.

Frames (:func:`select_frames`): the robot covers much of the view and the joint
configurations are far apart, so that every axis, the depth along the view included, is
constrained. Distances are measured in the robot's configuration space, the joint vectors
through the recipe's joint map (:meth:`~imac_data.core.robot.model.RobotModel.mapped_joints`:
radians, metres), so the choice does not depend on the units the joints were recorded in.
Degenerate sets are refused with a clear :class:`InputError`: no frame shows the robot, or too
few distinct configurations do.

Robot pixels (``RobotPixels``), a pluggable source:

* ``sim``: the simulator's ground truth recorded in the episodes (geom segmentation);
* ``masks``: a directory of masks from any segmenter, ``DIR/<episode>/<camera>/<frame:06d>.png``
  (nonzero = robot; ``<episode>`` is the episode file's stem); only frames with a mask are used;
* ``edges``: the built-in cue, no learned model: :func:`image_edges`, the image edges near
  the current overlay (Canny). The optimiser then pulls the rendered outline onto the
  nearest edge (:func:`imac_data.calibrate.optimise.refine_camera_edges`).

Frames are read from raw episodes (:class:`EpisodeFrames`, through
:class:`imac_data.sources.hdf5.EpisodeReader`) or from a LeRobot dataset
(:class:`DatasetFrames`, through LeRobot's ``LeRobotDataset``; ``<episode>`` in a mask
directory is then ``episode_000000``, ...), frame by frame and only where asked, so memory
follows the chosen frames, not the episodes' length. :func:`open_frames` picks the reader.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from imac_data import lerobot_compat as lr
from imac_data.core.cameras import Camera
from imac_data.core.depth import depth_codec_of
from imac_data.core.depth_map import depth_marker
from imac_data.core.masks import ground_truth_robot_mask
from imac_data.core.motion import joints_at
from imac_data.errors import InputError
from imac_data.layout import IMAGE_PREFIX, STATE, depth_key, info_path
from imac_data.recipes import DepthSection
from imac_data.sources.hdf5 import EpisodeReader, episode_paths
from imac_data.sources.lerobot_dataset import SourceDataset
from imac_data.sources.lerobot_episodes import DepthFeature, LeRobotEpisodeReader

__all__ = ["PIXEL_SOURCES", "EpisodeFrames", "DatasetFrames", "open_frames", "RobotPixels", "CameraFrames",
           "select_frames", "choose_frames", "image_edges"]

PIXEL_SOURCES = ("sim", "masks", "edges")
_BLOCK = 16  # frames read at once while scanning candidates (bounded memory)


# ----------------------------------------------------------------------------- sources


class EpisodeFrames:
    """The frames of raw ALOHA/AgileX HDF5 episodes (a directory, or one file).

    What refinement reads, and all it reads (another source provides the same):
    ``episodes`` (ids), ``cameras``, ``has_segmentation``, ``image_hw(cam)``, ``joints(ep)``,
    ``images(ep, cam, frames)``, ``robot_masks(ep, cam, frames, links)`` and
    ``mask_folder(ep)`` (the episode's name in a mask directory).
    """

    def __init__(self, source: str | Path):
        source = Path(source)
        if source.is_file():
            paths = [source]
        elif source.is_dir():
            paths = episode_paths(source)
        else:
            raise InputError(f"source not found: {source} (a directory of HDF5 episodes or one episode file)")
        self.source = source
        self.episodes = [str(p) for p in paths]
        cams, self._hw, self._seg = None, {}, True
        for p in paths:  # every episode is validated before any work
            with EpisodeReader(p) as ep:
                cams = set(ep.cameras) if cams is None else cams & set(ep.cameras)
                for c, hw in ep.image_hw.items():
                    if self._hw.setdefault(c, hw) != hw:
                        raise InputError(f"{p}: camera {c!r} has {hw[1]}x{hw[0]} images, an earlier episode "
                                         f"{self._hw[c][1]}x{self._hw[c][0]}")
                self._seg &= bool(ep.segmentation_labels()) and all(
                    ep.segmentation(c, 0, 1) is not None for c in ep.cameras)
        self.cameras = sorted(cams)
        self.has_segmentation = self._seg
        with EpisodeReader(paths[0]) as ep:  # the recorded rate (checked alike in every episode by the build)
            self.fps = ep.fps

    def _reader(self, episode: str):
        return EpisodeReader(episode)

    def image_hw(self, camera: str) -> tuple[int, int]:
        return self._hw[camera]

    def joints(self, episode: str) -> np.ndarray:
        """The measured joint vectors ``(T, D)``: what the images show."""
        with self._reader(episode) as ep:
            return ep.qpos

    def mask_folder(self, episode: str) -> str:
        return Path(episode).stem

    def images(self, episode: str, camera: str, frames: Sequence[int]) -> np.ndarray:
        with self._reader(episode) as ep:
            return np.concatenate([ep.images(camera, int(t), int(t) + 1) for t in frames])

    def robot_masks(self, episode: str, camera: str, frames: Sequence[int], links: Sequence[str]) -> np.ndarray:
        """The simulator's robot pixels ``(n, H, W)`` bool (geoms of the robot's links)."""
        with self._reader(episode) as ep:
            if ep.segmentation(camera, 0, 1) is None:
                raise InputError(f"{episode}: no ground-truth segmentation for camera {camera!r}; "
                                 "choose --robot-pixels edges or a mask directory")
            seg = np.concatenate([ep.segmentation(camera, int(t), int(t) + 1) for t in frames])
            return ground_truth_robot_mask(seg, ep.segmentation_labels(), links)


class DatasetFrames:
    """The frames of a LeRobot dataset (``ROOT/meta/info.json``), the same interface as
    :class:`EpisodeFrames`: joint vectors from ``observation.state``, images from the
    ``observation.images.<camera>`` streams, decoded by LeRobot, and its own depth
    (:meth:`depth_metres`): the recipe's ``depth.feature`` (a LeRobot 0.6 depth map, or
    millimetres, metres, our codec), else the depth stream an imac build wrote
    (``observation.depth.<camera>``). A dataset has no simulator segmentation, so its robot pixels
    are a mask directory or the edge cue."""

    has_segmentation = False
    _PREFIX = IMAGE_PREFIX

    def __init__(self, root: str | Path, depth: DepthSection | None = None):
        import json

        self.source = Path(root)
        path = info_path(self.source)
        if not path.is_file():
            raise InputError(f"{root} is not a LeRobot dataset ({path} is missing)")
        info = json.loads(path.read_text())
        features = info.get("features", {})
        keys = [k for k, f in features.items() if k.startswith(self._PREFIX) and f.get("dtype") in ("video", "image")
                and not depth_marker(f)]  # a LeRobot depth map is not a camera of its own
        if not keys:
            raise InputError(f"{path}: no {self._PREFIX}<camera> image streams")
        if STATE not in features:
            raise InputError(f"{path}: no observation.state feature (the joint vectors the images show)")
        self.cameras = sorted(k[len(self._PREFIX):] for k in keys)
        self._hw = {k[len(self._PREFIX):]: tuple(int(v) for v in features[k]["shape"][:2]) for k in keys}
        self.episodes = [str(i) for i in range(int(info.get("total_episodes", 0)))]
        self.fps = float(info["fps"]) if isinstance(info.get("fps"), (int, float)) else None
        if not self.episodes:
            raise InputError(f"{path}: the dataset has no episodes")
        self._open: tuple[str, object] | None = None  # one episode's LeRobotDataset at a time
        self._depth_config, self._depth = depth, None

    def _depth_feature(self) -> DepthFeature | None:
        """The dataset's depth of every camera, checked once (None: it records none)."""
        if self._depth is None:
            src, cfg = SourceDataset.open(self.source), self._depth_config
            if cfg is not None and cfg.feature is not None:
                feature = DepthFeature(cfg.feature, cfg.format, cfg.codec)
            elif all(depth_key(c) in src.features for c in self.cameras):
                feature = DepthFeature(depth_key("{cam}"), "codec")
                feature.codec = depth_codec_of(self.source)  # the codec this dataset was built with
            else:
                self._depth = False
                return None
            feature.check(src, self.cameras, f"{self.source}")
            self._depth = (src, feature)
        return self._depth[1] if self._depth else None

    def depth_metres(self, episode: str, camera: str, frames: Sequence[int]) -> np.ndarray | None:
        """The dataset's depth of ``camera`` at ``frames`` ``(n, H, W)`` in metres (0 = invalid), or None."""
        feature = self._depth_feature()
        if feature is None:
            return None
        src = self._depth[0]
        reader = LeRobotEpisodeReader(src, src.episodes[int(episode)], {camera: self._PREFIX + camera}, [], [], feature)
        with reader:
            depth = np.stack([reader.depth_mm(camera, int(t), int(t) + 1)[0] for t in frames]) / np.float32(1000.0)
        if depth.shape[1:] != self._hw[camera]:
            raise InputError(f"{self.source}: camera {camera!r}'s depth {feature.key(camera)} is {depth.shape[1:]}, "
                             f"its images {self._hw[camera]}: calibration needs them at one size")
        return depth

    def _dataset(self, episode: str):
        if self._open is None or self._open[0] != episode:
            self._open = (episode, lr.LeRobotDataset(f"local/{self.source.name}", root=self.source,
                                                     episodes=[int(episode)]))
        return self._open[1]

    def image_hw(self, camera: str) -> tuple[int, int]:
        return self._hw[camera]

    def joints(self, episode: str) -> np.ndarray:
        states = self._dataset(episode).hf_dataset[STATE]
        return torch.stack(list(states)).numpy().astype(np.float64)

    def mask_folder(self, episode: str) -> str:
        return f"episode_{int(episode):06d}"

    def images(self, episode: str, camera: str, frames: Sequence[int]) -> np.ndarray:
        ds = self._dataset(episode)
        out = []
        for t in frames:  # frame t of the episode is item t of its LeRobotDataset
            x = ds[int(t)][self._PREFIX + camera].numpy()
            out.append(np.clip(np.rint(np.moveaxis(x, 0, -1) * 255.0), 0, 255).astype(np.uint8))
        return np.stack(out)

    def robot_masks(self, episode: str, camera: str, frames: Sequence[int], links: Sequence[str]) -> np.ndarray:
        raise InputError(f"{self.source}: a LeRobot dataset carries no simulator segmentation; "
                         "choose --robot-pixels edges or a mask directory")


def open_frames(source: str | Path, depth: DepthSection | None = None) -> EpisodeFrames | DatasetFrames:
    """The frames of ``source``: a LeRobot dataset (a directory with ``meta/info.json``; ``depth``: the recipe's
    section, which names its depth feature), a directory of raw HDF5 episodes, or one episode file."""
    source = Path(source)
    if info_path(source).is_file():
        return DatasetFrames(source, depth)
    return EpisodeFrames(source)


@dataclass(frozen=True)
class RobotPixels:
    """Where the robot's pixels come from: ``kind`` in :data:`PIXEL_SOURCES`, and for
    ``masks`` the directory."""

    kind: str
    mask_dir: Path | None = None

    @classmethod
    def parse(cls, spec: str, frames) -> RobotPixels:
        """``auto`` (``sim`` when the episodes carry a segmentation, else ``edges``), ``sim``,
        ``edges`` or a mask directory."""
        if spec == "auto":
            spec = "sim" if getattr(frames, "has_segmentation", False) else "edges"
        if spec == "sim" and not getattr(frames, "has_segmentation", False):
            raise InputError(f"--robot-pixels sim: {frames.source} has no ground-truth segmentation; "
                             "choose edges or a mask directory")
        if spec in ("sim", "edges"):
            return cls(spec)
        if not Path(spec).is_dir():
            raise InputError(f"--robot-pixels {spec}: not 'auto', 'sim', 'edges' or a mask directory")
        return cls("masks", Path(spec))

    def __str__(self) -> str:
        return str(self.mask_dir) if self.kind == "masks" else self.kind

    def _mask_files(self, frames, episode: str, camera: str) -> dict[int, Path]:
        folder = self.mask_dir / frames.mask_folder(episode) / camera
        if not folder.is_dir():
            return {}
        return {int(p.stem): p for p in folder.glob("*.png") if p.stem.isdigit()}

    @staticmethod
    def _read_mask(path: Path, hw: tuple[int, int]) -> np.ndarray:
        m = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if m is None:
            raise InputError(f"{path}: not a readable PNG mask")
        if m.shape != tuple(hw):
            raise InputError(f"{path}: mask is {m.shape[1]}x{m.shape[0]}, the camera's frames are {hw[1]}x{hw[0]}")
        return m > 0


# ----------------------------------------------------------------------------- frame choice


def select_frames(q: np.ndarray, coverage: np.ndarray, count: int = 8, *, min_coverage: float = 0.01,
                  min_separation: float = 0.1, camera: str = "") -> np.ndarray:
    """Pick ``count`` frames for calibration: the robot covers much of the view and the joint
    configurations are far apart (different depths and directions constrain every axis).

    ``q`` ``(M, D)`` the candidate frames' configurations: their joint vectors through the
    robot's joint map (:meth:`~imac_data.core.robot.model.RobotModel.mapped_joints`, radians
    for revolute joints, metres for prismatic ones; :func:`choose_frames` maps them), so that
    the choice is the same whatever units the joints were recorded in. ``coverage`` ``(M,)``
    the fraction of each view the robot covers. Frames with coverage below ``min_coverage`` do
    not count; of the rest, the better-covered three quarters are candidates. Greedy
    farthest-point sampling in configuration space, starting at the best-covered frame; a
    frame closer than ``min_separation`` (radians, metres) to a chosen one is not a distinct
    pose. Returns candidate indices (sorted) or raises :class:`InputError` when the robot is
    not visible or too few distinct poses exist.
    """
    q = np.asarray(q, dtype=np.float64)
    coverage = np.asarray(coverage, dtype=np.float64)
    where = f" in camera {camera!r}" if camera else ""
    if q.ndim != 2 or coverage.shape != (len(q),):
        raise InputError(f"select_frames: q must be (M, D) and coverage (M,), got {q.shape} and {coverage.shape}")
    if count < 1:
        raise InputError(f"select_frames: count must be >= 1, got {count}")
    visible = np.flatnonzero(coverage >= min_coverage)
    if len(visible) == 0:
        best = float(coverage.max()) if len(coverage) else 0.0
        raise InputError(
            f"no robot visible{where}: in none of the {len(coverage)} candidate frames does the robot cover "
            f"{100 * min_coverage:.1f}% of the view (at most {100 * best:.2f}%). Refinement aligns the robot's "
            "silhouette, so it needs frames that show the robot (check the camera name and the robot-pixel source)")

    def greedy(pool: np.ndarray) -> list[int]:
        chosen = [int(pool[np.argmax(coverage[pool])])]
        dist = np.linalg.norm(q[pool] - q[chosen[0]], axis=1)
        while len(chosen) < count:
            k = int(np.argmax(dist))
            if dist[k] < min_separation:
                break
            chosen.append(int(pool[k]))
            dist = np.minimum(dist, np.linalg.norm(q[pool] - q[pool[k]], axis=1))
        return chosen

    good = visible[coverage[visible] >= np.quantile(coverage[visible], 0.25)]
    chosen = greedy(good)
    if len(chosen) < count:
        chosen = greedy(visible)
    if len(chosen) < count:
        raise InputError(
            f"too few distinct poses{where}: the frames that show the robot hold only {len(chosen)} joint "
            f"configuration(s) at least {min_separation} apart (radians after the joint map), and refinement "
            f"needs {count}. A camera pose is only pinned down by views of the robot in different configurations: use episodes where the arms "
            "move, more episodes, or ask for fewer frames (fewer constrain the pose less)")
    return np.sort(np.array(chosen, dtype=np.int64))


@dataclass
class CameraFrames:
    """The chosen frames of one camera: their joint vectors, images and robot pixels."""

    camera: str
    refs: list[tuple[str, int]]  # (episode, frame)
    q: np.ndarray  # (N, D)
    images: np.ndarray  # (N, H, W, 3) uint8
    target: np.ndarray | None  # (N, H, W) robot probability; None for the edge cue (made per round)


def _candidates(T: int, budget: int) -> np.ndarray:
    return np.arange(0, T, max(1, math.ceil(T / budget)))


def choose_frames(frames, camera: Camera, renderer, pixels: RobotPixels, count: int, *,
                  min_separation: float = 0.1, budget: int = 400, shift: float = 0.0) -> CameraFrames:
    """Choose ``count`` frames of ``camera`` (at the frames' resolution) over all episodes of
    ``frames`` and read their images and robot pixels. Coverage comes from the robot pixels
    (``sim``, ``masks``) or, for the edge cue, from the robot as the current calibration
    renders it. At most ``budget`` candidate frames are scanned, evenly spread. ``shift``: the
    camera's time offset in frames; each image is paired with the joint vectors at its own time,
    frame + ``shift``, as the build draws it (:func:`~imac_data.core.motion.joints_at`). Frames are
    spread by distance between the joint vectors mapped through the joint map of ``renderer``'s robot
    (:func:`select_frames`); the returned ``q`` are the recorded ones."""
    name, links = camera.name, renderer.link_names
    hw = frames.image_hw(name)
    per_episode = max(8, budget // len(frames.episodes))
    q_all, cov_all, refs = [], [], []
    for ep in frames.episodes:
        q = frames.joints(ep)
        if shift:
            q = joints_at(q, np.arange(len(q), dtype=np.float64) + shift)
        if pixels.kind == "masks":
            files = pixels._mask_files(frames, ep, name)
            idx = np.array(sorted(t for t in files if 0 <= t < len(q)), dtype=np.int64)
            idx = idx[_candidates(len(idx), per_episode)] if len(idx) else idx
            cov = [float(pixels._read_mask(files[t], hw).mean()) for t in idx]
        elif pixels.kind == "sim":
            idx = _candidates(len(q), per_episode)
            cov = np.concatenate([frames.robot_masks(ep, name, idx[i:i + _BLOCK], links).mean(axis=(1, 2))
                                  for i in range(0, len(idx), _BLOCK)])
        else:  # edges: where the current calibration renders the robot, at low resolution
            idx = _candidates(len(q), per_episode)
            cov = renderer.render(torch.as_tensor(q[idx]), {name: camera},
                                  resolution=(60, 80))[name].mask.float().mean(dim=(1, 2)).numpy()
        q_all.append(q[idx])
        cov_all.append(np.asarray(cov, dtype=np.float64))
        refs += [(ep, int(t)) for t in idx]
    if not refs:
        raise InputError(f"no robot visible in camera {name!r}: no frame has a mask under {pixels.mask_dir}")
    q_all = np.concatenate(q_all)
    sel = select_frames(renderer.robot.mapped_joints(q_all), np.concatenate(cov_all), count,
                        min_separation=min_separation, camera=name)
    chosen = [refs[i] for i in sel]
    images, target = [], []
    for ep in dict.fromkeys(e for e, _ in chosen):  # refs are in episode order, frames ascending
        ts = [t for e, t in chosen if e == ep]
        images.append(frames.images(ep, name, ts))
        if pixels.kind == "sim":
            target.append(frames.robot_masks(ep, name, ts, links))
        elif pixels.kind == "masks":
            files = pixels._mask_files(frames, ep, name)
            target.append(np.stack([pixels._read_mask(files[t], hw) for t in ts]))
    return CameraFrames(name, chosen, q_all[sel], np.concatenate(images),
                        np.concatenate(target).astype(np.float32) if target else None)


# ----------------------------------------------------------------------------- edge cue


def image_edges(images: np.ndarray, rendered: np.ndarray, *, margin_px: int, low: float = 20.0,
                high: float = 60.0) -> np.ndarray:
    """The built-in robot cue: image edges ``(N, H, W)`` bool near the robot as the current
    calibration renders it.

    ``images`` ``(N, H, W, 3)`` uint8; ``rendered`` ``(N, H, W)`` the robot rendered with the
    current calibration, off by up to about ``margin_px``. Canny edges (hysteresis thresholds
    ``low``, ``high`` on 8-bit intensity steps) of each colour channel, combined, kept within
    ``margin_px`` of the rendered robot: the robot's outline is among them, most of the
    scene's clutter is not. A colour model of the robot learnt from the overlay was tried
    first and dropped: simulated table shading alone made it label the table as robot.
    """
    images = np.asarray(images)
    rendered = np.asarray(rendered, dtype=bool)
    if images.ndim != 4 or images.shape[:3] != rendered.shape or images.shape[-1] != 3 or images.dtype != np.uint8:
        raise InputError(f"image_edges: images must be (N, H, W, 3) uint8 matching the masks "
                         f"{rendered.shape}, got {images.shape} {images.dtype}")
    if rendered.sum() < 50:
        raise InputError(f"the current calibration renders almost no robot ({int(rendered.sum())} pixels over "
                         f"{len(rendered)} frames): the edge cue looks for the robot's outline near the current "
                         "overlay, so the calibration must be roughly right (check it with `qa overlay`), or "
                         "give the robot's pixels as masks")
    margin_px = max(1, int(margin_px))
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * margin_px + 1, 2 * margin_px + 1))
    out = np.zeros(rendered.shape, dtype=bool)
    for img, m, o in zip(images, rendered, out):
        e = np.zeros(m.shape, np.uint8)
        for ch in cv2.split(cv2.GaussianBlur(img, (3, 3), 0)):
            e |= cv2.Canny(ch, low, high, L2gradient=True)
        near = cv2.dilate(m.astype(np.uint8), k) > 0
        np.logical_and(e > 0, near, out=o)
    return out
