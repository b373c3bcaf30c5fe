"""Raw HDF5 episodes -> a base LeRobot dataset (v3.0 format, LeRobot's own writer).

What lands in the dataset per frame: ``observation.state``, ``action``,
``observation.velocity`` (when recorded), ``observation.images.{cam}`` (video),
``camera_pose.{cam}`` (camera-to-world, OpenCV, 16 floats row-major; wrist
cameras posed by forward kinematics of the measured state) and the task string.
Per episode, in ``meta/episodes``: ``imac/source``, ``imac/policy_name``,
``imac/checkpoint``, ``imac/success``. In ``meta/info.json`` under ``imac``:
the robot description (name, content hash), the calibration and the builder version.

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
import pyarrow.parquet as pq
import torch
from tqdm.auto import tqdm

from imac_data.aloha_hdf5 import SOURCES, probe_episode, read_episode
from imac_data.cameras import Camera
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
    return root.parent / f".{root.name}.staging"


def check_episodes(paths: Sequence[Path], calibration: dict[str, Camera], robot: RobotModel) -> dict:
    """Validate every episode against each other, the calibration and the robot, without
    loading images. Returns the common probe (cameras, dof)."""
    if not paths:
        raise InputError("no episodes to ingest")
    first = probe_episode(paths[0])
    for path in paths[1:]:
        probe = probe_episode(path)
        if probe["cameras"] != first["cameras"]:
            raise InputError(
                f"episodes have different camera sets: {paths[0]} has {first['cameras']}, "
                f"{path} has {probe['cameras']}"
            )
        if probe["dof"] != first["dof"]:
            raise InputError(f"{path}: joint vector has {probe['dof']} entries, {paths[0]} has {first['dof']}")
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
    return first


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


def ingest_episodes(paths: Sequence[str | Path], *, rig, repo_id: str, root: str | Path, options: IngestOptions,
                    overwrite: bool = False, progress: bool = True):
    """Write ``paths`` (ALOHA HDF5 episodes) as a LeRobot dataset at ``root``, with the
    rig (:class:`~imac_data.rig.Rig`) in ``info["imac"]`` and its robot description under
    ``meta/imac/robot/``. Returns the loaded :class:`LeRobotDataset`."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from imac_data.dataset.info import base_block, update_imac_info
    from imac_data.robot_files import DESCRIPTION_DIR, write_description

    calibration, robot = rig.cameras, rig.robot
    paths = [Path(p) for p in paths]
    root = Path(root)
    if root.exists() and not overwrite:
        raise InputError(f"output {root} already exists (pass overwrite=True / --overwrite to replace it)")
    probe = check_episodes(paths, calibration, robot)
    if options.state_names is not None and len(options.state_names) != probe["dof"]:
        raise InputError(f"state_names has {len(options.state_names)} names for a {probe['dof']}-D joint vector")

    first = read_episode(paths[0], load_depth=False)
    image_hw = {cam: first.images[cam].shape[1:3] for cam in first.cameras}
    rig = rig.with_image_sizes(image_hw)
    calibration = rig.cameras
    features = _features(image_hw, probe["dof"], options.state_names, first.qvel is not None)

    staging = staging_dir(root)
    if staging.exists():
        shutil.rmtree(staging)
    staging.parent.mkdir(parents=True, exist_ok=True)
    dataset = None
    try:
        # LeRobot's standard writer (PNG frames, encoded per episode). Its streaming_encoding
        # option is faster but drops the last frame of an episode in 0.4.4.
        dataset = LeRobotDataset.create(
            repo_id=repo_id, fps=int(round(options.fps)), features=features, root=staging,
            robot_type=options.robot_type, use_videos=True, vcodec=options.vcodec,
        )
        episode_rows = []
        for path in tqdm(paths, desc="ingest episodes", unit="ep", disable=not progress):
            episode = first if path == paths[0] else read_episode(path, load_depth=False)
            if episode.cameras != first.cameras or any(
                episode.images[c].shape[1:3] != image_hw[c] for c in first.cameras
            ):
                raise InputError(f"{path}: image sizes differ from {paths[0]}")
            poses = camera_poses(calibration, robot, episode.qpos)
            info = episode.info
            task = info.task or options.task
            for t in range(episode.num_frames):
                frame = {
                    "observation.state": episode.qpos[t].astype(np.float32),
                    "action": episode.action[t].astype(np.float32),
                    "task": task,
                }
                if episode.qvel is not None:
                    frame["observation.velocity"] = episode.qvel[t].astype(np.float32)
                for cam in first.cameras:
                    frame[f"observation.images.{cam}"] = episode.images[cam][t]
                    frame[f"camera_pose.{cam}"] = poses[cam][t].reshape(16).astype(np.float32)
                dataset.add_frame(frame)
            dataset.save_episode()
            episode_rows.append({
                "imac/source": info.source or options.source,
                "imac/policy_name": info.policy_name or options.policy_name,
                "imac/checkpoint": info.checkpoint or options.checkpoint,
                "imac/success": info.success,
            })
            del episode
        dataset.finalize()
        add_episode_columns(staging, episode_rows)
        write_description(robot, staging / DESCRIPTION_DIR)
        update_imac_info(staging, base_block(rig))
        if root.exists():
            shutil.rmtree(root)
        staging.rename(root)
    except BaseException:
        if dataset is not None:
            _abandon(dataset)
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return LeRobotDataset(repo_id, root=root)


def _abandon(dataset) -> None:
    """Stop LeRobot's background writers (video encoder threads, parquet writers) so
    nothing writes into the staging directory after we delete it."""
    encoder = getattr(dataset, "_streaming_encoder", None)
    if encoder is not None:
        try:
            encoder.cancel_episode()
        finally:
            encoder.close()
    dataset._close_writer()
    dataset.meta._close_writer()


def add_episode_columns(root: Path, rows: list[dict]) -> None:
    """Append per-episode columns to LeRobot's ``meta/episodes`` parquet files."""
    for file in sorted((root / "meta" / "episodes").rglob("*.parquet")):
        table = pq.read_table(file)
        index = table.column("episode_index").to_pylist()
        for key in EPISODE_COLUMNS:
            values = [rows[i][key] for i in index]
            typ = pa.bool_() if key == "imac/success" else pa.string()
            if key in table.column_names:
                table = table.drop(key)
            table = table.append_column(key, pa.array(values, type=typ))
        pq.write_table(table, file)


def update_imac_info(root: Path, block: dict) -> None:
    """Merge ``block`` into the ``imac`` key of ``meta/info.json`` (see :mod:`imac_data.dataset.info`)."""
    from imac_data.dataset.info import update_imac_info as update

    update(root, block)
