"""The lift policies of the ranking benchmark: they act from observations only.

Each one localises the red cube (:mod:`.perception`) from the RGB and depth it is given,
plans the right arm's pick-and-lift (the waypoints of the simulated lift script) and follows
it through inverse kinematics, 8 actions per query at 10 fps; the left arm holds its start
configuration. The closed-loop ones re-localise on every observation and move their grasp
target until the fingers start to close; the open-loop ones localise once, from the first
observation, and grasp at a fixed offset from what they saw: the centimetre regime that
decides a grasp. ``docs/ranking.md`` lists them with their measured success."""

from __future__ import annotations

import numpy as np
import torch

from imac_data.core.mujoco_gl import mujoco
from imac_data.core.rig import Rig
from imac_data.core.robot.platforms import simulator_platform
from imac_data.layout import STATE, depth_key, image_key
from imac_data.sources.sim.rig import camera_calibration, load_mujoco_model
from imac_data.sources.sim.scripts import ArmIK, Trajectory, Waypoint, lift_waypoints
from imac_data.sources.sim.tasks import REST_HEIGHT, TABLE_Z
from imac_model.experiments.ranking.perception import cube_centre_xy, red_points

FPS = 10.0  # frames (actions) per second
CHUNK = 8  # actions per query: the world model's chunk
CLOSE_AT = 1.5  # seconds: the fingers start to close; closed-loop targets are fixed from here on
HEAD, WRIST = "cam_high", "cam_right_wrist"
MIN_WRIST_POINTS = 6  # red points the wrist view needs before it is trusted over the head view
TABLE_CENTRE = np.array([0.0, 0.5])  # where gym-aloha's cube sampler is centred: the guess when nothing is seen
LEFT, RIGHT_ARM, RIGHT_GRIP = slice(0, 7), slice(7, 13), 13


def lift_rig() -> Rig:
    """The simulated rig's cameras and kinematics: the policy's knowledge of its own robot."""
    model = load_mujoco_model("lift")
    return Rig.from_platform(simulator_platform(), camera_calibration(model, 640, 480), task="lift")


class LiftPolicy:
    """Pick the cube up with the right arm (see the module docstring).

    ``relocalise``: the views it localises from on every observation (None: open loop, the
    head view once); ``offset``: metres added to the grasp target in the table plane."""

    def __init__(self, name: str, *, relocalise: tuple[str, ...] | None = (HEAD, WRIST),
                 offset: tuple[float, float] = (0.0, 0.0)):
        self.name = name
        self.relocalise = tuple(relocalise) if relocalise else None
        self.offset = np.asarray(offset, dtype=np.float64)
        model = load_mujoco_model("lift")  # kinematics only; the policy never sees the simulator's state
        self.ik = ArmIK(model, "vx300s_right")
        self.rig = lift_rig()
        self.views = list(self.rig.cameras)
        self.reset()

    def reset(self) -> None:
        self.calls = 0
        self.cube: np.ndarray | None = None  # the current estimate of the cube's centre (x, y)
        self.targets: list[np.ndarray] = []  # the grasp target (x, y) after each query
        self.estimates: list[np.ndarray | None] = []  # what each observation showed
        self.trajectory: Trajectory | None = None

    def locate(self, observation: dict, views: tuple[str, ...]) -> np.ndarray | None:
        """The cube's centre (x, y) seen in ``views``: the wrist view when it shows enough of the
        cube, else the head view; None when neither shows it."""
        state = torch.as_tensor(observation[STATE]).float()
        rgb = observation[image_key(self.views[0])]
        K = self.rig.intrinsics(tuple(rgb.shape[-2:]))
        poses = self.rig.camera_poses(state[None])[0]
        for view, min_points in ((WRIST, MIN_WRIST_POINTS), (HEAD, 1)):
            if view not in views or image_key(view) not in observation:
                continue
            i = self.views.index(view)
            points, weights = red_points(observation[image_key(view)], observation[depth_key(view)], K[i], poses[i])
            xy = cube_centre_xy(points, weights, min_points)
            if xy is not None:
                return xy.double().numpy()
        return None

    def _plan(self, t0: float, home: tuple[np.ndarray, np.ndarray], grip0: float) -> Trajectory:
        cube = np.r_[self.cube + self.offset, TABLE_Z + REST_HEIGHT["box"]]
        waypoints = lift_waypoints(cube, home, grip0)
        if self.trajectory is None or t0 <= 0:
            return Trajectory(waypoints)
        pos, quat, grip = self.trajectory(t0)  # replan from where the arm is being sent now
        R = np.empty(9)
        mujoco.mju_quat2Mat(R, quat)
        return Trajectory([Waypoint(t0, pos, R.reshape(3, 3), grip)] + [w for w in waypoints if w.t > t0])

    def __call__(self, observation: dict) -> torch.Tensor:
        state = torch.as_tensor(observation[STATE]).double().numpy()
        t0 = self.calls * CHUNK / FPS
        if self.calls == 0:
            self.hold_left = state[LEFT].copy()
            self.q = state[RIGHT_ARM].copy()
            self.home = self.ik.fk(self.q)
            self.grip0 = float(state[RIGHT_GRIP])
        seen = None
        if self.calls == 0 or self.relocalise:
            seen = self.locate(observation, (HEAD,) if self.calls == 0 else self.relocalise)
        self.estimates.append(seen)
        replan = self.calls == 0 or (self.relocalise is not None and t0 < CLOSE_AT and seen is not None)
        if self.calls == 0 or replan:
            self.cube = seen if seen is not None else (self.cube if self.cube is not None else TABLE_CENTRE.copy())
            self.trajectory = self._plan(t0, self.home, self.grip0)
        self.targets.append(self.cube + self.offset)
        actions = np.empty((CHUNK, 14))
        for k in range(CHUNK):
            pos, quat, grip = self.trajectory(t0 + k / FPS)
            self.q = self.ik.solve(self.q, pos, quat)
            actions[k, LEFT] = self.hold_left
            actions[k, RIGHT_ARM] = self.q
            actions[k, RIGHT_GRIP] = grip
        self.calls += 1
        return torch.from_numpy(actions).float()


def _factory(name: str, **kwargs):
    def make() -> LiftPolicy:
        return LiftPolicy(name, **kwargs)

    make.is_factory = True
    make.__name__ = name
    return make


# The benchmark's policies, as `python:imac_model.experiments.ranking.policies:NAME`; offsets along world +y.
closed_loop = _factory("closed_loop")
closed_loop_1p5cm = _factory("closed_loop_1p5cm", offset=(0.0, 0.015))
open_loop = _factory("open_loop", relocalise=None)
open_loop_2cm = _factory("open_loop_2cm", relocalise=None, offset=(0.0, 0.02))
open_loop_2p5cm = _factory("open_loop_2p5cm", relocalise=None, offset=(0.0, 0.025))
open_loop_3cm = _factory("open_loop_3cm", relocalise=None, offset=(0.0, 0.03))

POLICIES = ("closed_loop", "closed_loop_1p5cm", "open_loop", "open_loop_2cm", "open_loop_2p5cm", "open_loop_3cm")
