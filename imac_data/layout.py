"""Where things are in an imac dataset and what its features are called, named once.

A built dataset is a LeRobot v3.0 dataset (``docs/dataset-format.md``): LeRobot's own files,
plus the added features below, the ``imac`` block in ``meta/imac/info.json`` and the robot
description under ``meta/imac/robot/``.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path

# ----------------------------------------------------------------------------- files
INFO = "meta/info.json"
STATS = "meta/stats.json"
TASKS = "meta/tasks.parquet"
EPISODES_DIR = "meta/episodes"
DATA_DIR = "data"
VIDEOS_DIR = "videos"
DEFAULT_VIDEO_PATH = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
IMAC_INFO = "meta/imac/info.json"  # the imac block (schema version 3 on; before, the "imac" key of meta/info.json)
DESCRIPTION_DIR = "meta/imac/robot"  # the robot description a dataset carries
URDF_NAME = "robot.urdf"
MESH_DIR = "meshes"
CALIBRATION = "calibration.json"  # beside raw episodes


def info_path(root: str | Path) -> Path:
    return Path(root) / INFO


def imac_info_path(root: str | Path) -> Path:
    return Path(root) / IMAC_INFO


def stats_path(root: str | Path) -> Path:
    return Path(root) / STATS


def episodes_dir(root: str | Path) -> Path:
    return Path(root) / EPISODES_DIR


def description_dir(root: str | Path) -> Path:
    return Path(root) / DESCRIPTION_DIR


def cache_home() -> Path:
    """Our cache: recorded simulator episodes, the exported ALOHA URDF, metric weights."""
    return Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "imac"


# ----------------------------------------------------------------------------- features
STATE = "observation.state"
ACTION = "action"
VELOCITY = "observation.velocity"
IMAGE_PREFIX = "observation.images."
DEPTH_PREFIX = "observation.depth."
DEPTH_MAP_PREFIX = "observation.depth_map."  # LeRobot 0.6 depth maps (augment.lerobot_depth_map)
CONTROL_PREFIX = "control."
MOTION = "control.motion"
R2S = "control.contact_r2s"
S2G = "control.contact_s2g"
CAP_KEY = "control.contact_cap"  # per frame: the (r2s, s2g) caps of the frame's chunk, metres
POSE_PREFIX = "camera_pose."  # per frame and camera: camera-to-world, OpenCV axes, row-major 4x4
POSE_NAMES = [f"m{r}{c}" for r in range(4) for c in range(4)]
EPISODE_COLUMNS = ("imac/source", "imac/policy_name", "imac/checkpoint", "imac/success")  # meta/episodes
SUCCESS_COLUMN = "imac/success"
SIM_COLUMNS = ("imac/sim_task", "imac/sim_seed", "imac/sim_settle_s")  # meta/episodes of episodes built from HDF5: a simulated start


def image_key(camera: str) -> str:
    return IMAGE_PREFIX + camera


def depth_key(camera: str) -> str:
    return DEPTH_PREFIX + camera


def depth_map_key(camera: str) -> str:
    return DEPTH_MAP_PREFIX + camera


def pose_key(camera: str) -> str:
    return POSE_PREFIX + camera


def control_key(stream: str, camera: str) -> str:
    """``control.<stream>.<camera>``; ``stream`` is ``motion``, ``contact_r2s`` or ``contact_s2g``."""
    return f"{CONTROL_PREFIX}{stream}.{camera}"


def stream_keys(cameras: Iterable[str], *, depth: bool = True, depth_maps: bool = False) -> list[str]:
    """The added video streams in the dataset's order: depth per camera (then, with
    ``depth_maps``, LeRobot depth maps per camera), then per camera motion, robot-to-scene,
    scene-to-gripper (``depth=False``: motion only)."""
    cameras = list(cameras)
    if not depth:
        return [f"{MOTION}.{c}" for c in cameras]
    maps = [depth_map_key(c) for c in cameras] if depth_maps else []
    return [depth_key(c) for c in cameras] + maps + [f"{k}.{c}" for c in cameras for k in (MOTION, R2S, S2G)]


def is_added_stream(key: str) -> bool:
    return key.startswith((CONTROL_PREFIX, DEPTH_PREFIX, DEPTH_MAP_PREFIX))


VIDEO_COLUMNS = "videos/"  # meta/episodes columns that locate an episode in a video feature's files
STATS_COLUMNS = "stats/"  # meta/episodes columns of per-episode feature statistics


def video_column(key: str, field: str) -> str:
    """A ``meta/episodes`` column locating an episode in a video feature's files
    (``chunk_index``, ``file_index``, ``from_timestamp``, ``to_timestamp``)."""
    return f"{VIDEO_COLUMNS}{key}/{field}"


def stats_column(key: str, stat: str) -> str:
    return f"{STATS_COLUMNS}{key}/{stat}"
