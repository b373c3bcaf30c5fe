"""Raw HDF5 episodes -> a base LeRobot dataset (v3.0 format), streamed.

What lands in the dataset per frame: ``observation.state``, ``action``,
``observation.velocity`` (when recorded), ``observation.images.{cam}`` (video),
``camera_pose.{cam}`` (camera-to-world, OpenCV, 16 floats row-major; wrist
cameras posed by forward kinematics of the measured state) and the task string.
Per episode, in ``meta/episodes``: ``imac/source``, ``imac/policy_name``,
``imac/checkpoint``, ``imac/success``. In ``meta/info.json`` under ``imac``:
the rig (robot, calibration, controller; :mod:`imac_data.dataset.info`), and the robot
description itself under ``meta/imac/robot/``.

The writer is LeRobot's own (parquet, metadata, stats, video layout) with our video
encoder in its streaming slot (:mod:`imac_data.dataset.episodes`): frames are read and
encoded a chunk at a time, with LeRobot's settings, never held for a whole episode, and no
PNG is written. The same :class:`BaseWriter` writes the base features of the build's
shards, where the control streams are added in the same pass (:mod:`imac_data.pipeline`).

Everything is checked before anything is written, the dataset is built in a
staging directory next to the destination and renamed into place only when it
is complete; on any error the staging directory is removed.
"""

from __future__ import annotations

import shutil
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa
import torch
from tqdm.auto import tqdm

from imac_data.aloha_hdf5 import SOURCES, probe_episode
from imac_data.cameras import Camera
from imac_data.dataset.columns import add_episode_columns
from imac_data.errors import InputError
from imac_data.robot import RobotModel

EPISODE_COLUMNS = ("imac/source", "imac/policy_name", "imac/checkpoint", "imac/success")


@dataclass(frozen=True)
class IngestOptions:
    """How to label and encode what the raw files do not say themselves."""

    fps: float
    task: str  # instruction used when an episode carries none
    source: str = "teleop"  # default episode source when the file carries none
    policy_name: str | None = None
    checkpoint: str | None = None
    robot_type: str | None = None
    state_names: tuple[str, ...] | None = None
    vcodec: str = "libsvtav1"

    def __post_init__(self) -> None:
        if not self.fps > 0:
            raise InputError(f"fps must be positive, got {self.fps}")
        if not self.task:
            raise InputError("task (the language instruction) must be a non-empty string")
        if self.source not in SOURCES:
            raise InputError(f"source must be one of {SOURCES}, got {self.source!r}")


def staging_dir(root: Path) -> Path:
    """Where a dataset for ``root`` is assembled before it is moved into place."""
    from imac_data.safety import output_sibling

    return output_sibling(root, "staging")


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


def camera_poses(calibration: dict[str, Camera], robot: RobotModel, qpos: np.ndarray) -> dict[str, np.ndarray]:
    """Per-frame camera-to-world poses ``(T, 4, 4)`` for every camera, wrist cameras by FK."""
    q = torch.as_tensor(qpos, dtype=torch.float64)
    links = robot.link_poses(q) if any(c.link for c in calibration.values()) else None
    return {
        name: cam.pose(links, batch_shape=(len(qpos),), dtype=torch.float64).numpy()
        for name, cam in calibration.items()
    }


def _features(probe_images: dict[str, tuple[int, int]], dof: int, names: Sequence[str] | None,
              with_velocity: bool) -> dict:
    names = list(names) if names is not None else [f"joint_{i}" for i in range(dof)]
    features = {
        "observation.state": {"dtype": "float32", "shape": (dof,), "names": names},
        "action": {"dtype": "float32", "shape": (dof,), "names": names},
    }
    if with_velocity:
        features["observation.velocity"] = {"dtype": "float32", "shape": (dof,), "names": names}
    for cam, (h, w) in probe_images.items():
        features[f"observation.images.{cam}"] = {
            "dtype": "video", "shape": (h, w, 3), "names": ["height", "width", "channels"],
        }
    for cam in probe_images:
        features[f"camera_pose.{cam}"] = {"dtype": "float32", "shape": (16,), "names": None}
    return features


class BaseWriter:
    """The base features of a new dataset at ``root``, episode by episode, frames as they
    come (LeRobot's writer with our streaming encoder, :class:`~imac_data.dataset.episodes.EpisodeWriter`).

    ``add(frames)`` takes a chunk of one episode: ``state``, ``action``, ``qvel`` (or None)
    ``(n, D)``, ``images`` ``{cam: (n, H, W, 3)}``, ``poses`` ``{cam: (n, 4, 4)}``.
    ``finish(rig)`` adds the episode columns, the robot description and the ``imac`` block.
    """

    def __init__(self, root: Path, repo_id: str, *, rig, image_hw: dict[str, tuple[int, int]], dof: int,
                 with_velocity: bool, options: IngestOptions, threads: int | None = None):
        from imac_data.dataset.episodes import EpisodeWriter

        self.root, self.options, self.cameras = Path(root), options, sorted(image_hw)
        features = _features({c: image_hw[c] for c in self.cameras}, dof, options.state_names, with_velocity)
        self.writer = EpisodeWriter(self.root, repo_id, fps=int(round(options.fps)), features=features,
                                    robot_type=options.robot_type, threads=threads)
        self.with_velocity = with_velocity
        self.rows: list[dict] = []

    def begin_episode(self, length: int, info) -> None:
        self.writer.begin_episode(length, task=info.task or self.options.task)
        o = self.options
        self.rows.append({"imac/source": info.source or o.source, "imac/policy_name": info.policy_name or o.policy_name,
                          "imac/checkpoint": info.checkpoint or o.checkpoint, "imac/success": info.success})

    def add(self, state, action, qvel, images, poses) -> None:
        rows = {"observation.state": np.asarray(state, np.float64).astype(np.float32),
                "action": np.asarray(action, np.float64).astype(np.float32)}
        if self.with_velocity:
            rows["observation.velocity"] = np.asarray(qvel, np.float64).astype(np.float32)
        for cam in self.cameras:
            rows[f"observation.images.{cam}"] = images[cam]
        for cam in self.cameras:
            rows[f"camera_pose.{cam}"] = poses[cam].reshape(len(state), 16).astype(np.float32)
        self.writer.add_frames(rows)

    def end_episode(self) -> None:
        self.writer.end_episode()

    def finish(self, rig, *, with_description: bool = True) -> None:
        from imac_data.dataset.info import base_block, update_imac_info
        from imac_data.robot_files import DESCRIPTION_DIR, write_description

        self.writer.finish()
        add_episode_columns(self.root, self.rows, {k: pa.bool_() if k == "imac/success" else pa.string()
                                                   for k in EPISODE_COLUMNS})
        if with_description:
            write_description(rig.robot, self.root / DESCRIPTION_DIR)
        update_imac_info(self.root, base_block(rig))

    def abort(self) -> None:
        self.writer.abort()


def ingest_episodes(paths: Sequence[str | Path], *, rig, repo_id: str, root: str | Path, options: IngestOptions,
                    overwrite: bool = False, progress: bool = True, chunk_frames: int = 32):
    """Write ``paths`` (ALOHA HDF5 episodes) as a LeRobot dataset at ``root``, with the
    rig (:class:`~imac_data.rig.Rig`) in ``info["imac"]`` and its robot description under
    ``meta/imac/robot/``, reading and encoding ``chunk_frames`` frames at a time. Returns the
    loaded :class:`LeRobotDataset`."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from imac_data.aloha_hdf5 import EpisodeReader
    from imac_data.safety import check_output, remove_sibling, swap_into_place

    paths = [Path(p) for p in paths]
    root = Path(root)
    check_output(root, overwrite=overwrite, what="output")  # replaces only a dataset; leftovers only ours
    probe = check_episodes(paths, rig.cameras, rig.robot)
    if options.state_names is not None and len(options.state_names) != probe["dof"]:
        raise InputError(f"state_names has {len(options.state_names)} names for a {probe['dof']}-D joint vector")
    with EpisodeReader(paths[0]) as first:
        image_hw, with_velocity = dict(first.image_hw), first.qvel is not None
    rig = rig.with_image_sizes(image_hw)

    staging = staging_dir(root)
    remove_sibling(staging)
    staging.parent.mkdir(parents=True, exist_ok=True)
    writer = None
    try:
        writer = BaseWriter(staging, repo_id, rig=rig, image_hw=image_hw, dof=probe["dof"],
                            with_velocity=with_velocity, options=options)
        for path in tqdm(paths, desc="ingest episodes", unit="ep", disable=not progress):
            with EpisodeReader(path) as ep:
                if ep.image_hw != image_hw:
                    raise InputError(f"{path}: image sizes {ep.image_hw} differ from {paths[0]}'s {image_hw}")
                writer.begin_episode(ep.num_frames, ep.info)
                for lo in range(0, ep.num_frames, chunk_frames):
                    hi = min(lo + chunk_frames, ep.num_frames)
                    poses = camera_poses(rig.cameras, rig.robot, ep.qpos[lo:hi])
                    writer.add(ep.qpos[lo:hi], ep.action[lo:hi], None if ep.qvel is None else ep.qvel[lo:hi],
                               {c: ep.images(c, lo, hi) for c in writer.cameras}, poses)
                writer.end_episode()
        writer.finish(rig)
        swap_into_place(staging, root)
    except BaseException:
        if writer is not None:
            writer.abort()
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return LeRobotDataset(repo_id, root=root)
