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
from imac_data.sources.sim.rig import RIG_CAMERAS, camera_calibration, load_mujoco_model
from imac_data.sources.sim.scripts import ArmIK, Trajectory, Waypoint, lift_waypoints
from imac_data.sources.sim.tasks import REST_HEIGHT, TABLE_Z, TASK_INSTRUCTIONS
from imac_model.experiments.ranking.perception import cube_centre_xy, red_points

FPS = 10.0  # frames (actions) per second
CHUNK = 8  # actions per query: the world model's chunk
CLOSE_AT = 1.5  # seconds: the fingers start to close; closed-loop targets are fixed from here on
WORKSPACE, WRIST = "cam_workspace", "cam_right_wrist"
# the cameras the policies localise from when they are given them; the benchmark gives them what the world model
# generates (RankingPlan.views: the workspace view alone by default, docs/ranking.md)
VIEWS = (WORKSPACE, WRIST)
MIN_WRIST_POINTS = 6  # red points the wrist view needs before it is trusted over the workspace view
TABLE_CENTRE = np.array([0.0, 0.5])  # where gym-aloha's cube sampler is centred: the guess when nothing is seen
LEFT, RIGHT_ARM, RIGHT_GRIP = slice(0, 7), slice(7, 13), 13


def lift_rig() -> Rig:
    """The simulated rig's cameras and kinematics: the policy's knowledge of its own robot."""
    model = load_mujoco_model("lift")
    return Rig.from_platform(simulator_platform(), camera_calibration(model, 640, 480, RIG_CAMERAS), task="lift")


class LiftPolicy:
    """Pick the cube up with the right arm (see the module docstring).

    ``relocalise``: the views it localises from on every observation (None: open loop, the
    workspace view once); ``offset``: metres added to the grasp target in the table plane."""

    tasks = (TASK_INSTRUCTIONS["lift"],)  # the runners refuse any other task before any work

    def __init__(self, name: str, *, relocalise: tuple[str, ...] | None = (WORKSPACE, WRIST),
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
        cube, else the workspace view; None when neither shows it."""
        state = torch.as_tensor(observation[STATE]).float()
        poses = self.rig.camera_poses(state[None])[0]
        for view, min_points in ((WRIST, MIN_WRIST_POINTS), (WORKSPACE, 1)):
            if view not in views or image_key(view) not in observation:
                continue
            i = self.views.index(view)
            K = self.rig.intrinsics(tuple(observation[image_key(view)].shape[-2:]))
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
            seen = self.locate(observation, (WORKSPACE,) if self.calls == 0 else self.relocalise)
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


# The benchmark's policies, as `python:imac_model.experiments.ranking.policies:NAME`; offsets along world +y, across
# the fingers. The grasp fails between 1.25 and 2.5 cm off (docs/ranking.md, "Success by grasp offset"), so the
# graded policies grasp there; the workspace view puts the cube within millimetres in either loop.
closed_loop = _factory("closed_loop")
open_loop = _factory("open_loop", relocalise=None)
open_loop_1p25cm = _factory("open_loop_1p25cm", relocalise=None, offset=(0.0, 0.0125))
closed_loop_1p5cm = _factory("closed_loop_1p5cm", offset=(0.0, 0.015))
open_loop_1p75cm = _factory("open_loop_1p75cm", relocalise=None, offset=(0.0, 0.0175))
closed_loop_1p9cm = _factory("closed_loop_1p9cm", offset=(0.0, 0.019))
open_loop_2p25cm = _factory("open_loop_2p25cm", relocalise=None, offset=(0.0, 0.0225))
open_loop_3cm = _factory("open_loop_3cm", relocalise=None, offset=(0.0, 0.03))
# the set before 2026-12-01 (the committed report's): three policies beyond the slope, all at 0
open_loop_3p5cm = _factory("open_loop_3p5cm", relocalise=None, offset=(0.0, 0.035))
open_loop_4cm = _factory("open_loop_4cm", relocalise=None, offset=(0.0, 0.04))

POLICIES = ("closed_loop", "open_loop_1p25cm", "closed_loop_1p5cm", "open_loop_1p75cm", "closed_loop_1p9cm",
            "open_loop_2p25cm", "open_loop_3cm")


# The world model's training rollouts: how far (metres, world x along the fingers, y across them) each grasps off
# the cube it sees. The offset across the fingers decides a grasp (docs/ranking.md, "What the view must show").
def _disc(rng: np.random.Generator) -> tuple[float, float]:
    """Up to 3.5 cm in any direction, uniform over the disc: the design before 2026-11-28. Only 4 of its 192
    rollouts grasp more than 3 cm off across the fingers, where three of the six policies grasp."""
    angle, radius = rng.uniform(0, 2 * np.pi), 0.035 * np.sqrt(rng.uniform())
    return float(radius * np.cos(angle)), float(radius * np.sin(angle))


def _across(rng: np.random.Generator) -> tuple[float, float]:
    """Up to 5 cm either way across the fingers and 2 cm along them, uniform: clear misses and clear grasps
    beside the near ones, so the model sees every regime a policy can grasp in."""
    return float(rng.uniform(-0.02, 0.02)), float(rng.uniform(-0.05, 0.05))


def _slope(rng: np.random.Generator) -> tuple[float, float]:
    """``across`` for half the rollouts; the other half 1-3 cm either way across the fingers, where the success
    rate falls (0.16 at -3..-2 cm, 0.64 and 0.12 at +1..+3 cm, docs/ranking.md, "Training data that covers the
    policies"): the outcome learned where it is in doubt, beside every regime."""
    if rng.uniform() < 0.5:
        return _across(rng)
    return float(rng.uniform(-0.02, 0.02)), float(rng.choice((-1.0, 1.0)) * rng.uniform(0.01, 0.03))


TRAINING_OFFSETS = {"disc": _disc, "across": _across, "slope": _slope}


def training_policy(index: int, offsets: str = "across") -> LiftPolicy:
    """The policy of training rollout ``index``: closed loop (both views or the workspace view alone) or open
    loop in turn, grasping at an offset drawn from ``TRAINING_OFFSETS[offsets]`` with the rollout's own seed."""
    rng = np.random.default_rng([index, 0x7A11])
    kind = index % 3
    relocalise = ((WORKSPACE, WRIST), (WORKSPACE,), None)[kind]
    return LiftPolicy(f"mix_{('closed_loop', 'closed_loop_head', 'open_loop')[kind]}", relocalise=relocalise,
                      offset=TRAINING_OFFSETS[offsets](rng))
