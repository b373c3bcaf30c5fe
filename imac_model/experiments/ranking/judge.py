"""The deterministic success judge of the lift: is the cube up in the air?

From the workspace view (a fixed, low side camera, where a successful lift moves the cube by
12-17 px at 48x64), the red pixels are lifted to the world with their depth and the camera's pose at the frame's state (edge pixels,
which mix the cube's colour with a finger's depth, left out). The cube is
held up when enough of those points lie near the right gripper's tool centre point (forward
kinematics of the same state) and their median height is at least the success height (the
cube's centre 4 cm above its resting height); red drawn anywhere else does not count. A frame
votes; the majority of the judged frames decides. The same judge reads real frames (depth rendered, recorded) and generated ones
(depth decoded from the generated colour depth), at the depth's size."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from imac_data.errors import InputError
from imac_data.layout import image_key
from imac_data.sources.sim.scripts import TCP_OFFSET
from imac_data.sources.sim.tasks import LIFT_HEIGHT, REST_HEIGHT, TABLE_Z
from imac_model.data import mosaic
from imac_model.evaluate.success import EpisodeFrames, SuccessJudge
from imac_model.experiments.ranking.perception import red_points
from imac_model.experiments.ranking.policies import WORKSPACE, lift_rig

MIN_POINTS = 10  # red points near the gripper a frame needs before it can vote "lifted"
NEAR = 0.06  # metres from the tool centre point: a held cube's surface (half side 2 cm, grasped up to 2 cm off centre)
GRIPPER_LINK = "vx300s_right/gripper_link"


class LiftJudge(SuccessJudge):
    """See the module docstring. ``view``: the camera it reads."""

    name = "lift_geometry"

    def __init__(self, view: str = WORKSPACE, *, min_points: int = MIN_POINTS, near: float = NEAR,
                 lifted_z: float = TABLE_Z + REST_HEIGHT["box"] + LIFT_HEIGHT):
        self.rig = lift_rig()
        self.views = list(self.rig.cameras)
        if view not in self.views:
            raise InputError(f"LiftJudge: view {view!r} is not one of the rig's cameras {self.views}")
        self.view, self.min_points, self.near, self.lifted_z = view, int(min_points), float(near), float(lifted_z)

    def tool_centre(self, states: torch.Tensor) -> torch.Tensor:
        """``(K, 3)`` the right gripper's tool centre point at ``states (K, 14)``."""
        T = self.rig.link_poses(states)[GRIPPER_LINK]
        return T[:, :3, :3] @ torch.as_tensor(TCP_OFFSET, dtype=T.dtype) + T[:, :3, 3]

    def heights(self, episode: EpisodeFrames) -> np.ndarray:
        """Per judged frame: the median height (m) of the cube's points near the gripper, NaN
        with too few."""
        key = image_key(self.view)
        if key not in episode.frames or not episode.depth or key not in episode.depth or episode.states is None:
            raise InputError(f"episode {episode.episode_index}: the lift judge needs {key}, its depth and the "
                             "states (episode_frames(..., geometry=True); the closed loop passes them)")
        depth, states = episode.depth[key], torch.as_tensor(episode.states).float()
        rgb = mosaic.resize_frames(torch.as_tensor(episode.frames[key]).float(), tuple(depth.shape[-2:]))
        i = self.views.index(self.view)
        K = self.rig.intrinsics(tuple(rgb.shape[-2:]))[i]
        poses = self.rig.camera_poses(states)[:, i]
        tcp = self.tool_centre(states)
        out = np.full(len(rgb), np.nan)
        for k in range(len(rgb)):
            points, _ = red_points(rgb[k], depth[k], K, poses[k], edges=False)
            points = points[(points - tcp[k]).norm(dim=-1) <= self.near]
            if len(points) >= self.min_points:
                out[k] = float(points[:, 2].median())
        return out

    def judge(self, episodes: Sequence[EpisodeFrames]) -> np.ndarray:
        votes = [self.heights(ep) >= self.lifted_z for ep in episodes]  # NaN votes "not lifted"
        return np.array([2 * int(v.sum()) > len(v) for v in votes], dtype=bool)


def lift_judge() -> LiftJudge:
    """The judge as ``python:imac_model.experiments.ranking.judge:lift_judge``."""
    return LiftJudge()


lift_judge.is_factory = True  # python_object calls it once to make the judge (as policies)
