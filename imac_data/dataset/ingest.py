"""The base features of a new dataset, episode by episode: what a raw episode becomes before
any stream is added.

Per frame: ``observation.state``, ``action``, ``observation.velocity`` (when recorded), the
camera videos ``observation.images.<cam>`` and the camera poses ``camera_pose.<cam>``; per
episode the ``imac/*`` columns; the rig in ``info["imac"]`` and the robot description under
``meta/imac/robot/``. Written by LeRobot's own writer with our streaming encoder
(:class:`~imac_data.dataset.episodes.EpisodeWriter`), a chunk at a time.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa

from imac_data.core.robot.description import write_description
from imac_data.dataset.columns import add_episode_columns
from imac_data.dataset.episodes import EpisodeWriter
from imac_data.dataset.info import base_block, update_imac_info
from imac_data.errors import InputError
from imac_data.layout import (
    ACTION,
    EPISODE_COLUMNS,
    SIM_COLUMNS,
    STATE,
    SUCCESS_COLUMN,
    VELOCITY,
    description_dir,
    image_key,
    pose_key,
)
from imac_data.sources.hdf5 import SOURCES

__all__ = ["IngestOptions", "BaseWriter", "write_rig", "episode_column_types", "sim_column_types"]


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


def episode_column_types() -> dict[str, pa.DataType]:
    """The arrow types of the ``imac/*`` episode columns."""
    return {k: pa.bool_() if k == SUCCESS_COLUMN else pa.string() for k in EPISODE_COLUMNS}


def sim_column_types() -> dict[str, pa.DataType]:
    """The arrow types of the simulated start's columns (null for recorded episodes)."""
    return dict(zip(SIM_COLUMNS, (pa.string(), pa.int64(), pa.float64())))


def write_rig(root: Path, rig, *, with_description: bool = True) -> None:
    """The rig into the dataset at ``root``: its ``info["imac"]`` block and (unless a merge
    brings it later) the robot description under ``meta/imac/robot/``."""
    if with_description:
        write_description(rig.robot, description_dir(root))
    update_imac_info(root, base_block(rig))


def _features(image_hw: dict[str, tuple[int, int]], dof: int, names: Sequence[str] | None,
              with_velocity: bool) -> dict:
    names = list(names) if names is not None else [f"joint_{i}" for i in range(dof)]
    features = {
        STATE: {"dtype": "float32", "shape": (dof,), "names": names},
        ACTION: {"dtype": "float32", "shape": (dof,), "names": names},
    }
    if with_velocity:
        features[VELOCITY] = {"dtype": "float32", "shape": (dof,), "names": names}
    for cam, (h, w) in image_hw.items():
        features[image_key(cam)] = {"dtype": "video", "shape": (h, w, 3), "names": ["height", "width", "channels"]}
    for cam in image_hw:
        features[pose_key(cam)] = {"dtype": "float32", "shape": (16,), "names": None}
    return features


class BaseWriter:
    """The base features of a new dataset at ``root``, episode by episode, frames as they come.

    ``add`` takes a chunk of one episode: ``state``, ``action``, ``qvel`` (or None) ``(n, D)``,
    ``images`` ``{cam: (n, H, W, 3)}``, ``poses`` ``{cam: (n, 4, 4)}``. ``finish(rig)`` adds
    the episode columns and the rig.
    """

    def __init__(self, root: Path, repo_id: str, *, image_hw: dict[str, tuple[int, int]], dof: int,
                 with_velocity: bool, options: IngestOptions, threads: int | None = None):
        self.root, self.options, self.cameras = Path(root), options, sorted(image_hw)
        features = _features({c: image_hw[c] for c in self.cameras}, dof, options.state_names, with_velocity)
        self.writer = EpisodeWriter(self.root, repo_id, fps=int(round(options.fps)), features=features,
                                    robot_type=options.robot_type, threads=threads)
        self.with_velocity = with_velocity
        self.rows: list[dict] = []

    def begin_episode(self, length: int, info) -> None:
        self.writer.begin_episode(length, task=info.task or self.options.task)
        o = self.options
        values = (info.source or o.source, info.policy_name or o.policy_name, info.checkpoint or o.checkpoint,
                  info.success)
        self.rows.append({**dict(zip(EPISODE_COLUMNS, values)),
                          **dict(zip(SIM_COLUMNS, (info.sim_task, info.sim_seed, info.sim_settle_s)))})

    def add(self, state, action, qvel, images, poses) -> None:
        rows = {STATE: np.asarray(state, np.float64).astype(np.float32),
                ACTION: np.asarray(action, np.float64).astype(np.float32)}
        if self.with_velocity:
            rows[VELOCITY] = np.asarray(qvel, np.float64).astype(np.float32)
        for cam in self.cameras:
            rows[image_key(cam)] = images[cam]
        for cam in self.cameras:
            rows[pose_key(cam)] = poses[cam].reshape(len(state), 16).astype(np.float32)
        self.writer.add_frames(rows)

    def end_episode(self) -> None:
        self.writer.end_episode()

    def finish(self, rig, *, with_description: bool = True) -> None:
        self.writer.finish()
        add_episode_columns(self.root, self.rows, {**episode_column_types(), **sim_column_types()})
        write_rig(self.root, rig, with_description=with_description)

    def abort(self) -> None:
        self.writer.abort()
