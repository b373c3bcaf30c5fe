"""Scripted-policy recorder: simulated ALOHA episodes of the gym-aloha tasks, written
as ALOHA HDF5 files (see :mod:`imac_data.aloha_hdf5`), so the whole pipeline runs
on a fresh machine without real robot data.

Policy
------
gym-aloha ships no scripted policies, so this module has the ACT-style ones:
end-effector waypoints (approach, descend, grasp, lift, meet, hand over / insert)
computed from the objects' initial poses, interpolated with a minimum-jerk
profile (position) and slerp (orientation). The targets are turned into joint
targets by damped-least-squares IK on MuJoCo Jacobians of the *joint-position*
model itself, warm-started from the previous solution, and sent to gym-aloha's
position actuators. We chose IK over ACT's "run the mocap model, then replay its
joints" because (a) one simulation pass produces the episode, so the recorded
``action`` is exactly the command the recorded physics received and the success
label comes from that same rollout (ACT's replay can diverge from the mocap run
and fail silently), (b) the mocap weld is soft, so its joint trajectories carry
the weld's lag, not a controller's, and (c) it halves the physics cost.
The scripts are open loop except one step: during insertion, once the arms are
at the meeting point, the right arm servoes the peg onto the socket's axis from
the observed object poses (grasp slip and the arms' gravity sag otherwise
misalign them by about a centimetre, more than the socket's 8 mm clearance).
Default episodes last 5.0 s (transfer_cube) and 4.6 s (insertion).

Object poses are drawn with gym-aloha's own samplers (``sample_box_pose`` /
``sample_insertion_pose``) seeded with the episode seed, so episode ``i`` of a
dataset with ``seed=s`` starts exactly like ``gym_aloha`` ``env.reset(seed=s + i)``.

``noise`` in [0, 1] degrades the policy: Gaussian errors in the perceived object
positions (grasp offsets, sigma 12 mm * noise), per-arm meeting-point errors, a
bias in the observed peg-socket offset, slowly varying (Ornstein-Uhlenbeck,
0.3 s) joint-target noise (0.03 rad * noise), and tempo jitter. Measured success
over seeds 0-29: noise 0: 30/30 both tasks; 0.25: 29/30 transfer_cube, 25/30
insertion; 0.5: 19/30 and 10/30; 1.0: 1/30 and 0/30.
The success label is read off the simulator (contacts and object poses at the
end of the rollout), never from the script's intent.

Recording, frames and actions
-----------------------------
Physics runs at 500 Hz with 50 Hz control (``CONTROL_DT``), as in gym-aloha.
With ``frame_stride = s`` the policy is queried every ``s`` control steps and its
command is held (zero-order hold) for those ``s`` steps, so for recorded frame
``k`` (time ``k * s * CONTROL_DT``):

* ``qpos[k]``, ``qvel[k]``, images, depth, segmentation: the state *before*
  ``action[k]`` is applied;
* ``action[k]``: the command applied during ``[k s dt, (k + 1) s dt)``, i.e.
  exactly what drove the robot from frame ``k`` to frame ``k + 1``.

``fps = 1 / (s * CONTROL_DT)``. qpos/qvel/action use gym-aloha's 14-D layout
with the normalised gripper (0 closed, 1 open; velocities divided by the open -
close span, as gym-aloha's ``get_qvel``); arm actions are joint-position targets.

Depth is MuJoCo's depth buffer linearised by :class:`mujoco.Renderer`: planar
z-depth along the camera axis (checked against the analytic table plane in the
tests), stored as uint16 millimetres (rounded) like the AgileX Cobot Magic
records it. Pixels where nothing was hit (the far plane) or whose depth exceeds
the uint16 range (65.535 m) are stored as 0 = invalid. Depth is only defined
beyond the camera's near plane (``znear * extent`` = 0.166 m for this scene);
closer geometry is clipped in RGB and depth alike, as in gym-aloha.

Segmentation stores the MuJoCo geom id per pixel (-1 for background and non-geom
objects) with ``segmentation_labels`` {geom id: (geom name, body name)}.

Rendering uses one :class:`mujoco.Renderer` per dataset (one resolution) reused
for all cameras and frames: an RGB, a depth and optionally a segmentation pass
per camera. gym-aloha's 4096 px shadow map and 4x multisampling make the CPU
(Mesa llvmpipe) RGB pass ~10x slower, so by default we render without shadows
and multisampling; ``shadows=True`` / ``antialias=True`` restore them. Measured on
an idle 2-core CPU machine at 240x320: ~45 ms per frame for three views of RGB +
depth (~60 ms with segmentation), physics + IK ~3 ms per frame, i.e. ~6 s for a
default 125-frame episode.
"""

from __future__ import annotations

import argparse
import math
import time
from dataclasses import dataclass, fields
from pathlib import Path

import imac_data  # noqa: F401  (sets MUJOCO_GL before mujoco is imported)
import mujoco
import numpy as np

from imac_data.aloha import (
    ARM_JOINTS,
    ARMS,
    CAMERA_NAMES,
    CONTROL_DT,
    GRIPPER_CLOSE,
    GRIPPER_OPEN,
    TASKS,
    camera_calibration,
    load_mujoco_model,
    normalize_gripper,
    unnormalize_gripper,
)
from imac_data.aloha_hdf5 import EpisodeInfo, RawEpisode, write_episode
from imac_data.cameras import save_calibration
from imac_data.errors import InputError

__all__ = [
    "TASK_INSTRUCTIONS",
    "SimConfig",
    "EpisodeResult",
    "ScriptedPolicy",
    "FrameRenderer",
    "simulate_episode",
    "record_dataset",
    "robot_mask",
    "segmentation_labels",
    "depth_to_mm",
    "main",
]

# Instructions of LeRobot's aloha_sim datasets (lerobot/aloha_sim_*), which
# gym-aloha's tasks come from.
TASK_INSTRUCTIONS = {
    "transfer_cube": "Pick up the cube with the right arm and transfer it to the left arm.",
    "insertion": "Insert the peg into the socket.",
}

TABLE_Z = 0.0  # the table top (gym-aloha's tabletop mesh spans z in [-0.03, 0])

# Tool centre point in the gripper_link frame: between the finger pads, 2.4 cm
# behind the finger tips (which reach x = 0.154). All waypoints target this point.
TCP_OFFSET = np.array([0.13, 0.0, 0.0])

# Height of each object's centre above the table when it rests there.
_REST_HEIGHT = {"box": 0.02, "peg": 0.01, "socket": 0.022}

ROBOT_PREFIXES = tuple(ARMS)  # bodies of the vx300s_left / vx300s_right subtrees


# --------------------------------------------------------------------------- rotations


def _quat_from_mat(R: np.ndarray) -> np.ndarray:
    q = np.empty(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(R, dtype=np.float64).ravel())
    return q


def _rot_x(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _rot_y(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rot_z(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def _slerp(q0: np.ndarray, q1: np.ndarray, u: float) -> np.ndarray:
    d = float(np.dot(q0, q1))
    if d < 0.0:
        q1, d = -q1, -d
    if d > 0.9995:
        q = q0 + u * (q1 - q0)
        return q / np.linalg.norm(q)
    theta = math.acos(d)
    return (math.sin((1 - u) * theta) * q0 + math.sin(u * theta) * q1) / math.sin(theta)


def _min_jerk(u: float) -> float:
    u = min(max(u, 0.0), 1.0)
    return u * u * u * (10.0 + u * (-15.0 + 6.0 * u))


# --------------------------------------------------------------------------- IK


class _ArmIK:
    """Damped-least-squares IK of one arm's tool centre point (position + orientation)."""

    def __init__(self, model: mujoco.MjModel, arm: str):
        self.model = model
        self.data = mujoco.MjData(model)  # scratch: kinematics only
        jids = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, f"{arm}/{j}") for j in ARM_JOINTS]
        self.qadr = model.jnt_qposadr[jids]
        self.dadr = model.jnt_dofadr[jids]
        self.lo, self.hi = model.jnt_range[jids].T.copy()
        self.body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, f"{arm}/gripper_link")
        self._jacp = np.zeros((3, model.nv))
        self._jacr = np.zeros((3, model.nv))

    def fk(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """TCP position and gripper_link rotation matrix at arm joints ``q``."""
        self.data.qpos[self.qadr] = q
        mujoco.mj_kinematics(self.model, self.data)
        R = self.data.xmat[self.body].reshape(3, 3).copy()
        return self.data.xpos[self.body] + R @ TCP_OFFSET, R

    def solve(self, q0: np.ndarray, pos: np.ndarray, quat: np.ndarray, *, iters: int = 40,
              damping: float = 0.02, tol: float = 1e-5) -> np.ndarray:
        m, d = self.model, self.data
        q = np.array(q0, dtype=np.float64)
        err = np.empty(6)
        rot_err = np.empty(3)
        cur_quat = np.empty(4)
        for _ in range(iters):
            d.qpos[self.qadr] = q
            mujoco.mj_kinematics(m, d)
            mujoco.mj_comPos(m, d)
            R = d.xmat[self.body].reshape(3, 3)
            tcp = d.xpos[self.body] + R @ TCP_OFFSET
            err[:3] = pos - tcp
            mujoco.mju_mat2Quat(cur_quat, d.xmat[self.body])
            mujoco.mju_subQuat(rot_err, quat, cur_quat)  # in the current gripper frame
            err[3:] = R @ rot_err
            if err @ err < tol * tol:
                break
            mujoco.mj_jac(m, d, self._jacp, self._jacr, tcp, self.body)
            J = np.vstack([self._jacp[:, self.dadr], self._jacr[:, self.dadr]])
            dq = J.T @ np.linalg.solve(J @ J.T + damping**2 * np.eye(6), err)
            step = np.max(np.abs(dq))
            if step > 0.2:
                dq *= 0.2 / step
            q = np.clip(q + dq, self.lo, self.hi)
        return q


# --------------------------------------------------------------------------- scripts


@dataclass
class _Waypoint:
    t: float  # seconds
    pos: np.ndarray  # TCP position (world)
    R: np.ndarray  # gripper_link rotation (world)
    grip: float  # normalised gripper command


class _Trajectory:
    def __init__(self, waypoints: list[_Waypoint]):
        self.wps = waypoints
        self.quats = [_quat_from_mat(w.R) for w in waypoints]
        self.duration = waypoints[-1].t

    def __call__(self, t: float) -> tuple[np.ndarray, np.ndarray, float]:
        wps = self.wps
        if t <= wps[0].t:
            return wps[0].pos, self.quats[0], wps[0].grip
        for i in range(1, len(wps)):
            if t <= wps[i].t:
                a, b = wps[i - 1], wps[i]
                u = (t - a.t) / max(b.t - a.t, 1e-9)
                s = _min_jerk(u)
                pos = a.pos + s * (b.pos - a.pos)
                quat = _slerp(self.quats[i - 1], self.quats[i], s)
                grip = a.grip + u * (b.grip - a.grip)  # grippers ramp linearly
                return pos, quat, grip
        return wps[-1].pos, self.quats[-1], wps[-1].grip


def _home_rotations() -> dict[str, np.ndarray]:
    # Level grippers pointing at the centre of the table (+x for the left arm,
    # -x for the right arm, whose base is turned 180 degrees about z).
    return {"vx300s_left": np.eye(3), "vx300s_right": _rot_z(180.0)}


def _transfer_cube_script(objects: dict[str, np.ndarray], home: dict, rng: np.random.Generator,
                          noise: float) -> dict[str, list[_Waypoint]]:
    """Right arm picks the cube, brings it to the meeting point; left arm takes it."""
    H = _home_rotations()
    pick_R = H["vx300s_right"] @ _rot_y(60.0)  # pitched 60 degrees down
    meet_left_R = H["vx300s_left"] @ _rot_x(90.0)  # rolled: fingers close vertically
    cube = objects["box"] + rng.normal(0.0, 0.012 * noise, 3) * np.array([1.0, 1.0, 0.3])
    meet = np.array([0.0, 0.5, 0.25])
    meet_r = meet + rng.normal(0.0, 0.008 * noise, 3)
    meet_l = meet + rng.normal(0.0, 0.008 * noise, 3)
    grasp_z = max(cube[2], TABLE_Z + 0.02)
    g0 = home["grip"]
    right = [
        _Waypoint(0.0, home["vx300s_right"][0], home["vx300s_right"][1], g0),
        _Waypoint(1.0, np.array([cube[0], cube[1], grasp_z + 0.08]), pick_R, 1.0),  # approach
        _Waypoint(1.5, np.array([cube[0], cube[1], grasp_z]), pick_R, 1.0),  # descend
        _Waypoint(1.9, np.array([cube[0], cube[1], grasp_z]), pick_R, 0.0),  # close
        _Waypoint(2.1, np.array([cube[0], cube[1], grasp_z]), pick_R, 0.0),  # squeeze
        _Waypoint(2.7, meet_r + np.array([0.05, 0.0, 0.0]), pick_R, 0.0),  # lift, approach meet
        _Waypoint(3.0, meet_r, pick_R, 0.0),  # meet
        _Waypoint(3.9, meet_r, pick_R, 0.0),  # hold while the left arm grasps
        _Waypoint(4.2, meet_r, pick_R, 1.0),  # open
        _Waypoint(4.6, meet_r + np.array([0.1, 0.0, 0.0]), pick_R, 1.0),  # retreat
        _Waypoint(5.0, meet_r + np.array([0.1, 0.0, 0.0]), pick_R, 1.0),
    ]
    left = [
        _Waypoint(0.0, home["vx300s_left"][0], home["vx300s_left"][1], g0),
        _Waypoint(1.6, meet_l + np.array([-0.12, 0.0, 0.0]), meet_left_R, 1.0),  # approach meet
        _Waypoint(3.0, meet_l + np.array([-0.12, 0.0, 0.0]), meet_left_R, 1.0),
        _Waypoint(3.4, meet_l + np.array([0.0, 0.0, 0.0]), meet_left_R, 1.0),  # move in
        _Waypoint(3.8, meet_l + np.array([0.0, 0.0, 0.0]), meet_left_R, 0.0),  # close
        _Waypoint(4.2, meet_l + np.array([0.0, 0.0, 0.0]), meet_left_R, 0.0),  # hold while right opens
        _Waypoint(4.7, meet_l + np.array([-0.1, 0.0, 0.02]), meet_left_R, 0.0),  # take it away
        _Waypoint(5.0, meet_l + np.array([-0.1, 0.0, 0.02]), meet_left_R, 0.0),
    ]
    return {"vx300s_left": left, "vx300s_right": right}


def _insertion_script(objects: dict[str, np.ndarray], home: dict, rng: np.random.Generator,
                      noise: float) -> dict[str, list[_Waypoint]]:
    """Right arm picks the peg, left arm the socket; they meet and the peg goes in."""
    H = _home_rotations()
    pick_R = {arm: H[arm] @ _rot_y(60.0) for arm in ARMS}
    scale = np.array([1.0, 1.0, 0.3])
    peg = objects["peg"] + rng.normal(0.0, 0.012 * noise, 3) * scale
    socket = objects["socket"] + rng.normal(0.0, 0.012 * noise, 3) * scale
    meet = np.array([0.0, 0.5, 0.15])
    meet_r = meet + rng.normal(0.0, 0.006 * noise, 3)
    meet_l = meet + rng.normal(0.0, 0.006 * noise, 3)
    # Grasp heights: the finger tips reach ~2.1 cm below the TCP at 60 degrees pitch.
    peg_z = TABLE_Z + 0.022
    socket_z = TABLE_Z + 0.026
    peg_off = peg_z - objects["peg"][2]  # object centre sits this far below the TCP
    socket_off = socket_z - objects["socket"][2]
    g0 = home["grip"]
    # Peg centre 0.10 m right of the socket centre: peg tip meets the pin's end.
    r_in = meet_r + np.array([0.05, 0.0, peg_off - socket_off])
    l_in = meet_l + np.array([-0.05, 0.0, 0.0])
    right = [
        _Waypoint(0.0, home["vx300s_right"][0], home["vx300s_right"][1], g0),
        _Waypoint(1.2, np.array([peg[0], peg[1], peg_z + 0.08]), pick_R["vx300s_right"], 1.0),
        _Waypoint(1.7, np.array([peg[0], peg[1], peg_z]), pick_R["vx300s_right"], 1.0),
        _Waypoint(2.1, np.array([peg[0], peg[1], peg_z]), pick_R["vx300s_right"], 0.0),
        _Waypoint(2.3, np.array([peg[0], peg[1], peg_z]), pick_R["vx300s_right"], 0.0),
        _Waypoint(3.2, r_in + np.array([0.06, 0.0, 0.0]), pick_R["vx300s_right"], 0.0),
        _Waypoint(4.2, r_in + np.array([-0.015, 0.0, 0.0]), pick_R["vx300s_right"], 0.0),
        _Waypoint(4.6, r_in + np.array([-0.015, 0.0, 0.0]), pick_R["vx300s_right"], 0.0),
    ]
    left = [
        _Waypoint(0.0, home["vx300s_left"][0], home["vx300s_left"][1], g0),
        _Waypoint(1.2, np.array([socket[0], socket[1], socket_z + 0.08]), pick_R["vx300s_left"], 1.0),
        _Waypoint(1.7, np.array([socket[0], socket[1], socket_z]), pick_R["vx300s_left"], 1.0),
        _Waypoint(2.1, np.array([socket[0], socket[1], socket_z]), pick_R["vx300s_left"], 0.0),
        _Waypoint(2.3, np.array([socket[0], socket[1], socket_z]), pick_R["vx300s_left"], 0.0),
        _Waypoint(3.2, l_in + np.array([-0.06, 0.0, 0.0]), pick_R["vx300s_left"], 0.0),
        _Waypoint(4.2, l_in, pick_R["vx300s_left"], 0.0),
        _Waypoint(4.6, l_in, pick_R["vx300s_left"], 0.0),
    ]
    return {"vx300s_left": left, "vx300s_right": right}


_SCRIPTS = {"transfer_cube": _transfer_cube_script, "insertion": _insertion_script}


class ScriptedPolicy:
    """Open-loop waypoint policy for one episode; ``policy(t)`` returns the 14-D action
    (joint-position targets + normalised gripper commands) at time ``t`` seconds."""

    def __init__(self, task: str, model: mujoco.MjModel, data: mujoco.MjData,
                 rng: np.random.Generator, noise: float = 0.0):
        if task not in TASKS:
            raise InputError(f"unknown task {task!r}; expected one of {TASKS}")
        self.layout = layout = _Layout(model, task)
        self.noise = float(noise)
        self.rng = rng
        self.ik = {arm: _ArmIK(model, arm) for arm in ARMS}
        self.q = {arm: data.qpos[self.ik[arm].qadr].copy() for arm in ARMS}
        home = {arm: self.ik[arm].fk(self.q[arm]) for arm in ARMS}
        home["grip"] = float(normalize_gripper(data.qpos[layout.finger_qadr[0]]))
        # Objects spawn above the table and drop straight down: plan for their resting height.
        objects = {}
        for name, bid in layout.object_bodies.items():
            objects[name] = data.xpos[bid].copy()
            objects[name][2] = TABLE_Z + _REST_HEIGHT[name]
        scripts = _SCRIPTS[task](objects, home, rng, self.noise)
        # Tempo jitter: a noisy operator is not uniformly paced.
        self.tempo = 1.0 + self.noise * rng.uniform(-0.1, 0.1)
        self.traj = {arm: _Trajectory(wps) for arm, wps in scripts.items()}
        self.duration = max(tr.duration for tr in self.traj.values()) * self.tempo
        self._ou = np.zeros(14)
        self._t_last: float | None = None
        # Observation-based alignment (insertion only), see _servo.
        self.align_after = 3.2 if task == "insertion" else None
        self.perception_bias = rng.normal(0.0, 0.004 * self.noise, 3)
        self.correction = np.zeros(3)
        self._t_servo: float | None = None

    def _servo(self, t: float, data: mujoco.MjData | None) -> None:
        """Insertion: once the arms are at the meeting point, servo the peg onto the
        socket's axis (in the socket's cross-section plane) from the observed object
        poses, as an operator does by eye. Grasp slip and the arms' gravity sag would
        otherwise misalign them by about a centimetre."""
        if data is None or self.align_after is None or t / self.tempo < self.align_after:
            self._t_servo = None
            return
        dt = 0.0 if self._t_servo is None else t - self._t_servo
        self._t_servo = t
        pb, sb = self.layout.object_bodies["peg"], self.layout.object_bodies["socket"]
        Rs = data.xmat[sb].reshape(3, 3)
        rel = Rs.T @ (data.xpos[pb] - data.xpos[sb]) + self.perception_bias
        err = -(Rs @ np.array([0.0, rel[1], rel[2]]))
        self.correction = np.clip(self.correction + 8.0 * dt * err, -0.03, 0.03)

    def __call__(self, t: float, data: mujoco.MjData | None = None) -> np.ndarray:
        """The action at time ``t`` (s); ``data`` (the current simulator state) lets the
        insertion policy align the peg with the socket by observation."""
        self._servo(t, data)
        action = np.empty(14)
        for i, arm in enumerate(ARMS):
            pos, quat, grip = self.traj[arm](t / self.tempo)
            if arm == "vx300s_right":
                pos = pos + self.correction
            self.q[arm] = self.ik[arm].solve(self.q[arm], pos, quat)
            action[7 * i: 7 * i + 6] = self.q[arm]
            action[7 * i + 6] = grip
        if self.noise > 0.0:
            dt = CONTROL_DT if self._t_last is None else max(t - self._t_last, 1e-6)
            tau = 0.3
            sigma = np.r_[np.full(6, 0.03), 0.05, np.full(6, 0.03), 0.05] * self.noise
            self._ou += -self._ou * dt / tau + sigma * math.sqrt(2.0 * dt / tau) * self.rng.standard_normal(14)
            action += self._ou
        self._t_last = t
        for i, arm in enumerate(ARMS):
            ik = self.ik[arm]
            action[7 * i: 7 * i + 6] = np.clip(action[7 * i: 7 * i + 6], ik.lo, ik.hi)
        action[[6, 13]] = np.clip(action[[6, 13]], 0.0, 1.0)
        return action


# --------------------------------------------------------------------------- model layout


class _Layout:
    """Indices of the 14-D ALOHA vectors in a gym-aloha joint model."""

    def __init__(self, model: mujoco.MjModel, task: str):
        def jid(name):
            return mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, name)

        self.arm_qadr, self.arm_dadr, self.finger_qadr, self.finger_dadr = [], [], [], []
        self.actuators = []
        for arm in ARMS:
            ids = [jid(f"{arm}/{j}") for j in ARM_JOINTS]
            self.arm_qadr.append(model.jnt_qposadr[ids])
            self.arm_dadr.append(model.jnt_dofadr[ids])
            lf, rf = jid(f"{arm}/left_finger"), jid(f"{arm}/right_finger")
            self.finger_qadr.append(model.jnt_qposadr[lf])
            self.finger_dadr.append(model.jnt_dofadr[lf])
            trn = model.actuator_trnid[:, 0]
            act = [int(np.flatnonzero(trn == j)[0]) for j in (*ids, lf, rf)]
            self.actuators.append(np.array(act))
        self.qpos14 = np.r_[self.arm_qadr[0], self.finger_qadr[0], self.arm_qadr[1], self.finger_qadr[1]]
        self.qvel14 = np.r_[self.arm_dadr[0], self.finger_dadr[0], self.arm_dadr[1], self.finger_dadr[1]]
        self.gripper_cols = np.array([6, 13])
        names = {"transfer_cube": ("box",), "insertion": ("peg", "socket")}[task]
        self.object_bodies = {n: mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, n) for n in names}
        if min(self.object_bodies.values()) < 0:
            raise InputError(f"the MuJoCo model is not gym-aloha's {task!r} model (no body {names})")
        self.object_qadr = {
            n: model.jnt_qposadr[model.body_jntadr[b]] for n, b in self.object_bodies.items()
        }

        def geoms(pred):
            return {g for g in range(model.ngeom) if pred(model.geom(g).name, model.body(model.geom_bodyid[g]).name)}

        self.table = geoms(lambda g, b: g == "table")
        self.fingers = {arm: geoms(lambda g, b, arm=arm: b.startswith(f"{arm}/") and "finger" in g) for arm in ARMS}
        self.box = geoms(lambda g, b: b == "box")
        self.peg = geoms(lambda g, b: b == "peg")
        self.socket = geoms(lambda g, b: b == "socket" and g.startswith("socket"))
        self.pin = geoms(lambda g, b: g == "pin")

    def qpos(self, data: mujoco.MjData) -> np.ndarray:
        q = data.qpos[self.qpos14].copy()
        q[self.gripper_cols] = normalize_gripper(q[self.gripper_cols])
        return q

    def qvel(self, data: mujoco.MjData) -> np.ndarray:
        v = data.qvel[self.qvel14].copy()
        v[self.gripper_cols] /= GRIPPER_OPEN - GRIPPER_CLOSE
        return v

    def apply(self, data: mujoco.MjData, action: np.ndarray) -> None:
        """Write a 14-D action to the position actuators (as gym-aloha's ``before_step``)."""
        for i in range(2):
            a = action[7 * i: 7 * i + 7]
            finger = unnormalize_gripper(a[6])
            data.ctrl[self.actuators[i]] = np.r_[a[:6], finger, -finger]


# --------------------------------------------------------------------------- success


def _contact_pairs(data: mujoco.MjData) -> set[tuple[int, int]]:
    n = data.ncon
    if n == 0:
        return set()
    g1 = data.contact.geom1[:n]
    g2 = data.contact.geom2[:n]
    return {(int(a), int(b)) for a, b in zip(g1, g2)} | {(int(b), int(a)) for a, b in zip(g1, g2)}


def _touch(pairs, a: set[int], b: set[int]) -> bool:
    return any((x, y) in pairs for x in a for y in b)


def _task_reward(layout: _Layout, data: mujoco.MjData, task: str) -> int:
    """gym-aloha's staged reward (0..4) from the current contacts, with either finger of
    a gripper counting as that gripper."""
    pairs = _contact_pairs(data)
    left, right = layout.fingers["vx300s_left"], layout.fingers["vx300s_right"]
    if task == "transfer_cube":
        touch_right = _touch(pairs, layout.box, right)
        touch_left = _touch(pairs, layout.box, left)
        touch_table = _touch(pairs, layout.box, layout.table)
        reward = 0
        if touch_right:
            reward = 1
        if touch_right and not touch_table:
            reward = 2
        if touch_left:
            reward = 3
        if touch_left and not touch_table:
            reward = 4
        return reward
    touch_right = _touch(pairs, layout.peg, right)
    touch_left = _touch(pairs, layout.socket, left)
    peg_table = _touch(pairs, layout.peg, layout.table)
    socket_table = _touch(pairs, layout.socket, layout.table)
    peg_socket = _touch(pairs, layout.peg, layout.socket)
    reward = 0
    if touch_left and touch_right:
        reward = 1
    if touch_left and touch_right and not peg_table and not socket_table:
        reward = 2
    if peg_socket and not peg_table and not socket_table:
        reward = 3
    if _touch(pairs, layout.peg, layout.pin):
        reward = 4
    return reward


def _insertion_depth(layout: _Layout, data: mujoco.MjData) -> float:
    """How far (m) the peg's end is inside the socket tube (negative: outside/misaligned)."""
    pb, sb = layout.object_bodies["peg"], layout.object_bodies["socket"]
    Rs = data.xmat[sb].reshape(3, 3)
    p = Rs.T @ (data.xpos[pb] - data.xpos[sb])
    axis = Rs.T @ data.xmat[pb].reshape(3, 3)[:, 0]
    if abs(p[1]) > 0.012 or abs(p[2]) > 0.012 or abs(axis[0]) < math.cos(math.radians(20)):
        return -1.0
    return 0.12 - abs(p[0])  # socket half-length 0.06 + peg half-length 0.06


def _success(layout: _Layout, data: mujoco.MjData, task: str) -> bool:
    """The label, from the final simulator state.

    transfer_cube: the cube touches a left-gripper finger, no right-gripper finger and not
    the table, and its centre is at least 5 cm above the table top (held by the left arm alone).
    insertion: neither object touches the table and the peg's end is at least 1 cm inside the
    socket tube, axes aligned within 20 degrees (gym-aloha's reward only asks for a
    peg-pin touch at some instant; we want the peg to *be* in the socket at the end).
    """
    pairs = _contact_pairs(data)
    if task == "transfer_cube":
        box_z = data.xpos[layout.object_bodies["box"]][2]
        return (
            _touch(pairs, layout.box, layout.fingers["vx300s_left"])
            and not _touch(pairs, layout.box, layout.fingers["vx300s_right"])
            and not _touch(pairs, layout.box, layout.table)
            and box_z > TABLE_Z + 0.05
        )
    off_table = not (_touch(pairs, layout.peg, layout.table) or _touch(pairs, layout.socket, layout.table))
    return off_table and _insertion_depth(layout, data) > 0.01


# --------------------------------------------------------------------------- rendering


class FrameRenderer:
    """RGB / depth / segmentation of the three ALOHA cameras with one reused
    :class:`mujoco.Renderer` (one resolution)."""

    def __init__(self, model: mujoco.MjModel, width: int, height: int, *, depth: bool = True,
                 segmentation: bool = False, shadows: bool = False, antialias: bool = False,
                 cameras: dict[str, str] = CAMERA_NAMES):
        # Render settings live in the model's visual options (read when the GL context
        # is made); load_mujoco_model returns a private copy, so changing them is safe.
        model.vis.global_.offwidth = max(int(model.vis.global_.offwidth), width)
        model.vis.global_.offheight = max(int(model.vis.global_.offheight), height)
        if not shadows:
            model.vis.quality.shadowsize = 0
        if not antialias:
            model.vis.quality.offsamples = 0
        self.model = model
        self.width, self.height = width, height
        self.with_depth, self.with_segmentation = depth, segmentation
        self.cameras = dict(cameras)
        self.renderer = mujoco.Renderer(model, height=height, width=width)
        self._option = mujoco.MjvOption()
        self._option.sitegroup[:] = 0  # sites are invisible markers; keep them out of every pass
        self.far = float(model.vis.map.zfar * model.stat.extent)

    def render(self, data: mujoco.MjData) -> dict[str, dict[str, np.ndarray]]:
        """``{"rgb": {cam: (H,W,3) uint8}, "depth_mm": {cam: (H,W) uint16}, "segmentation": {cam: (H,W) int16}}``."""
        r = self.renderer
        out = {"rgb": {}, "depth_mm": {}, "segmentation": {}}
        for mj_cam, name in self.cameras.items():
            r.update_scene(data, camera=mj_cam, scene_option=self._option)
            out["rgb"][name] = r.render()
            if self.with_depth:
                r.enable_depth_rendering()
                depth = r.render()
                r.disable_depth_rendering()
                out["depth_mm"][name] = depth_to_mm(depth, self.far)
            if self.with_segmentation:
                r.enable_segmentation_rendering()
                seg = r.render()
                r.disable_segmentation_rendering()
                ids = np.where(seg[..., 1] == int(mujoco.mjtObj.mjOBJ_GEOM), seg[..., 0], -1)
                out["segmentation"][name] = ids.astype(np.int16)
        return out

    def close(self) -> None:
        self.renderer.close()

    def __enter__(self) -> FrameRenderer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def depth_to_mm(depth_m: np.ndarray, far: float) -> np.ndarray:
    """Planar z-depth in metres -> uint16 millimetres; far-plane (no hit), non-finite and
    beyond-range (> 65.535 m) pixels become 0 (invalid)."""
    mm = np.rint(np.asarray(depth_m, dtype=np.float64) * 1000.0)
    invalid = ~np.isfinite(mm) | (depth_m >= 0.999 * far) | (mm > 65535) | (mm <= 0)
    mm[invalid] = 0
    return mm.astype(np.uint16)


def segmentation_labels(model: mujoco.MjModel) -> dict[int, tuple[str, str]]:
    """{geom id: (geom name, body name)} of every geom of the model."""
    return {g: (model.geom(g).name, model.body(model.geom_bodyid[g]).name) for g in range(model.ngeom)}


def robot_mask(segmentation: np.ndarray, labels: dict[int, tuple[str, str]]) -> np.ndarray:
    """Boolean mask of the pixels showing the robot: geoms whose body is ``vx300s_left`` /
    ``vx300s_right`` or one of their descendants (gym-aloha names those ``vx300s_left/...``).

    ``segmentation`` is any-shaped int geom ids (-1 = none); ``labels`` {geom id: (geom, body)}.
    """
    seg = np.asarray(segmentation)
    robot_ids = [
        int(g) for g, (_, body) in labels.items()
        if any(body == p or body.startswith(p + "/") for p in ROBOT_PREFIXES)
    ]
    if not robot_ids:
        return np.zeros(seg.shape, dtype=bool)
    lut = np.zeros(max(max(robot_ids), int(seg.max(initial=-1))) + 2, dtype=bool)
    lut[np.array(robot_ids) + 1] = True  # shift by one so -1 (background) indexes lut[0]
    return lut[np.clip(seg.astype(np.int64), -1, None) + 1]


# --------------------------------------------------------------------------- episodes


@dataclass
class EpisodeResult:
    qpos: np.ndarray  # (T, 14)
    qvel: np.ndarray  # (T, 14)
    action: np.ndarray  # (T, 14)
    success: bool
    max_reward: int
    fps: float
    images: dict[str, np.ndarray]
    depth_mm: dict[str, np.ndarray]
    segmentation: dict[str, np.ndarray]
    final_object_pos: dict[str, np.ndarray]

    @property
    def num_frames(self) -> int:
        return int(self.qpos.shape[0])


def _initial_object_poses(task: str, seed: int) -> np.ndarray:
    from gym_aloha.utils import sample_box_pose, sample_insertion_pose

    if task == "transfer_cube":
        return sample_box_pose(seed)
    return np.concatenate(sample_insertion_pose(seed))


def _reset(model: mujoco.MjModel, data: mujoco.MjData, layout: _Layout, task: str, seed: int) -> None:
    """gym-aloha's episode start: START_ARM_POSE, ctrl = that pose, objects from its sampler."""
    from gym_aloha.constants import START_ARM_POSE

    mujoco.mj_resetData(model, data)
    start = np.asarray(START_ARM_POSE, dtype=np.float64)
    data.qpos[:16] = start
    data.ctrl[:16] = start
    poses = _initial_object_poses(task, seed).reshape(-1, 7)
    for (name, adr), pose in zip(layout.object_qadr.items(), poses):
        data.qpos[adr: adr + 7] = pose
    mujoco.mj_forward(model, data)


def simulate_episode(task: str, seed: int, *, noise: float = 0.0, frame_stride: int = 2,
                     max_steps: int | None = None, renderer: FrameRenderer | None = None,
                     model: mujoco.MjModel | None = None) -> EpisodeResult:
    """Roll out the scripted policy once. Without ``renderer`` nothing is rendered (fast:
    physics + IK only); with one, every recorded frame gets RGB (+ depth, segmentation)."""
    if task not in TASKS:
        raise InputError(f"unknown task {task!r}; expected one of {TASKS}")
    if renderer is not None:
        if model is not None and model is not renderer.model:
            raise InputError("simulate_episode: pass either model or renderer (which has its own model), not both")
        model = renderer.model
    elif model is None:
        model = load_mujoco_model(task)
    if frame_stride < 1:
        raise InputError(f"frame_stride must be >= 1, got {frame_stride}")
    data = mujoco.MjData(model)
    layout = _Layout(model, task)
    _reset(model, data, layout, task, seed)
    # The policy's noise stream is separate from the object-pose sampler (seeded with seed).
    rng = np.random.default_rng([int(seed), 0x51D])
    policy = ScriptedPolicy(task, model, data, rng, noise)
    n_steps = int(round(policy.duration / CONTROL_DT))
    if max_steps is not None:
        n_steps = min(n_steps, int(max_steps))
    n_frames = n_steps // frame_stride
    substeps = max(1, int(round(CONTROL_DT / model.opt.timestep)))  # 10, as gym-aloha
    qpos = np.empty((n_frames, 14))
    qvel = np.empty((n_frames, 14))
    action = np.empty((n_frames, 14))
    frames: list[dict] = []
    max_reward = 0
    for k in range(n_frames):
        qpos[k] = layout.qpos(data)
        qvel[k] = layout.qvel(data)
        if renderer is not None:
            frames.append(renderer.render(data))
        a = policy(k * frame_stride * CONTROL_DT, data)
        action[k] = a
        layout.apply(data, a)
        for _ in range(frame_stride):
            mujoco.mj_step(model, data, nstep=substeps)
            max_reward = max(max_reward, _task_reward(layout, data, task))
    success = _success(layout, data, task)

    def stack(kind):
        if not frames or not frames[0][kind]:
            return {}
        return {cam: np.stack([f[kind][cam] for f in frames]) for cam in frames[0][kind]}

    return EpisodeResult(
        qpos=qpos, qvel=qvel, action=action, success=bool(success), max_reward=max_reward,
        fps=1.0 / (frame_stride * CONTROL_DT),
        images=stack("rgb"), depth_mm=stack("depth_mm"), segmentation=stack("segmentation"),
        final_object_pos={n: data.xpos[b].copy() for n, b in layout.object_bodies.items()},
    )


# --------------------------------------------------------------------------- datasets


@dataclass(frozen=True)
class SimConfig:
    """What :func:`record_dataset` records. Validated on construction (:class:`InputError`
    naming the field)."""

    task: str = "transfer_cube"
    num_episodes: int = 2
    width: int = 320
    height: int = 240
    seed: int = 0  # episode i uses seed + i (object poses as gym-aloha's reset(seed=seed + i))
    noise: float = 0.0  # policy quality knob in [0, 1]; 0 = exact
    frame_stride: int = 2  # record every n-th 50 Hz control step (2 -> 25 fps)
    max_steps: int | None = None  # cap on 50 Hz control steps per episode (None: the whole script)
    with_depth: bool = True
    with_segmentation: bool = False
    compress: bool = False  # JPEG-compressed RGB (ALOHA's compressed variant)
    jpeg_quality: int = 95
    shadows: bool = False  # gym-aloha's shadow map (about 10x slower RGB on the CPU)
    antialias: bool = False  # 4x multisampling (about 2x slower RGB on the CPU)

    def __post_init__(self) -> None:
        def bad(name, why):
            raise InputError(f"SimConfig.{name}: {why} (got {getattr(self, name)!r})")

        def is_int(v):
            return isinstance(v, (int, np.integer)) and not isinstance(v, bool)

        if self.task not in TASKS:
            bad("task", f"must be one of {TASKS}")
        for name, lo, hi in (("num_episodes", 1, None), ("width", 16, 4096), ("height", 16, 4096),
                             ("frame_stride", 1, 50), ("jpeg_quality", 1, 100), ("seed", 0, 2**32 - 1)):
            v = getattr(self, name)
            if not is_int(v):
                bad(name, "must be an integer")
            if v < lo or (hi is not None and v > hi):
                bad(name, f"must be in [{lo}, {hi if hi is not None else 'inf'}]")
        if self.seed + self.num_episodes - 1 > 2**32 - 1:
            bad("seed", "seed + num_episodes - 1 must fit in 32 bits (gym-aloha's samplers)")
        if self.max_steps is not None:
            if not is_int(self.max_steps):
                bad("max_steps", "must be an integer or None")
            if self.max_steps < self.frame_stride:
                bad("max_steps", f"must be at least frame_stride ({self.frame_stride}) to record a frame")
        if isinstance(self.noise, bool) or not isinstance(self.noise, (int, float, np.floating)):
            bad("noise", "must be a number in [0, 1]")
        if not (math.isfinite(self.noise) and 0.0 <= self.noise <= 1.0):
            bad("noise", "must be in [0, 1]")
        for f in fields(self):
            if f.type in ("bool",) and not isinstance(getattr(self, f.name), (bool, np.bool_)):
                bad(f.name, "must be a bool")

    @property
    def fps(self) -> float:
        return 1.0 / (self.frame_stride * CONTROL_DT)


def _episode_path(out_dir: Path, index: int) -> Path:
    return out_dir / f"episode_{index}.hdf5"


def record_dataset(config: SimConfig, out_dir: str | Path, progress: bool = True, *,
                   overwrite: bool = False) -> list[Path]:
    """Record ``config.num_episodes`` scripted episodes into ``out_dir`` as
    ``episode_{i}.hdf5`` plus ``calibration.json`` (the rig at the recorded resolution).

    Every file is written atomically (temporary name, then renamed), so an interrupted
    run leaves only complete episodes. A directory that already holds episodes is
    refused unless ``overwrite`` (which first deletes its ``episode_*.hdf5``).
    """
    from tqdm.auto import tqdm

    if not isinstance(config, SimConfig):
        raise InputError(f"config must be a SimConfig, got {type(config).__name__}")
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(f"output path exists and is not a directory: {out_dir}")
    out_dir.mkdir(parents=True, exist_ok=True)
    existing = sorted(out_dir.glob("episode_*.hdf5"))
    if existing:
        if not overwrite:
            raise InputError(
                f"{out_dir} already holds {len(existing)} episode file(s); choose an empty directory "
                "or pass overwrite=True (--overwrite)"
            )
        for p in existing:
            p.unlink()

    model = load_mujoco_model(config.task)
    calib_tmp = out_dir / ".calibration.json.tmp"
    save_calibration(calib_tmp, camera_calibration(model, config.width, config.height))
    calib_tmp.replace(out_dir / "calibration.json")

    renderer = FrameRenderer(model, config.width, config.height, depth=config.with_depth,
                             segmentation=config.with_segmentation, shadows=config.shadows,
                             antialias=config.antialias)
    labels = segmentation_labels(model) if config.with_segmentation else {}
    paths = []
    bar = tqdm(range(config.num_episodes), desc=f"simulating {config.task}", unit="episode",
               disable=not progress)
    successes = 0
    try:
        for i in bar:
            result = simulate_episode(config.task, config.seed + i, noise=config.noise,
                                      frame_stride=config.frame_stride, max_steps=config.max_steps,
                                      renderer=renderer)
            successes += result.success
            episode = RawEpisode(
                qpos=result.qpos, qvel=result.qvel, action=result.action, images=result.images,
                depth_mm=result.depth_mm, segmentation=result.segmentation,
                segmentation_labels=labels,
                info=EpisodeInfo(task=TASK_INSTRUCTIONS[config.task], source="policy",
                                 policy_name=f"scripted_{config.task}", success=result.success),
                fps=result.fps,
            )
            path = _episode_path(out_dir, i)
            try:
                write_episode(path, episode, compress=config.compress, jpeg_quality=config.jpeg_quality)
            except BaseException:
                # write_episode writes to a temporary name first; don't leave it behind.
                path.with_name(f".{path.name}.tmp").unlink(missing_ok=True)
                raise
            paths.append(path)
            bar.set_postfix(success=f"{successes}/{i + 1}")
    finally:
        renderer.close()
        bar.close()
    return paths


# --------------------------------------------------------------------------- CLI


def _parse_args(argv: list[str] | None) -> argparse.Namespace:
    d = SimConfig()
    p = argparse.ArgumentParser(
        prog="python -m imac_data.simulate",
        description="Record scripted gym-aloha episodes (RGB, depth, optional segmentation) as ALOHA HDF5.",
    )
    p.add_argument("--task", default=d.task, help=f"one of {TASKS} (default {d.task})")
    p.add_argument("--episodes", type=int, default=d.num_episodes, help="number of episodes")
    p.add_argument("--out", required=True, type=Path, help="output directory")
    p.add_argument("--width", type=int, default=d.width)
    p.add_argument("--height", type=int, default=d.height)
    p.add_argument("--seed", type=int, default=d.seed, help="episode i uses seed + i")
    p.add_argument("--noise", type=float, default=d.noise, help="policy noise in [0, 1] (0 = exact)")
    p.add_argument("--frame-stride", type=int, default=d.frame_stride,
                   help="record every n-th 50 Hz control step (default 2 = 25 fps)")
    p.add_argument("--max-steps", type=int, default=None, help="cap on 50 Hz control steps per episode")
    p.add_argument("--segmentation", action="store_true", help="also store geom-id segmentation")
    p.add_argument("--no-depth", action="store_true", help="do not render depth")
    p.add_argument("--compress", action="store_true", help="store RGB as JPEG (ALOHA compressed variant)")
    p.add_argument("--shadows", action="store_true", help="render gym-aloha's shadows (slow on the CPU)")
    p.add_argument("--antialias", action="store_true", help="4x multisampled RGB")
    p.add_argument("--overwrite", action="store_true", help="replace episodes already in --out")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    from imac_data.cli import run_command

    args = _parse_args(argv)
    return run_command(lambda: _run(args))  # exit 2 bad input, 3 environment (disk full, ...)


def _run(args: argparse.Namespace) -> int:
    config = SimConfig(
        task=args.task, num_episodes=args.episodes, width=args.width, height=args.height,
        seed=args.seed, noise=args.noise, frame_stride=args.frame_stride, max_steps=args.max_steps,
        with_depth=not args.no_depth, with_segmentation=args.segmentation, compress=args.compress,
        shadows=args.shadows, antialias=args.antialias,
    )
    t0 = time.perf_counter()
    paths = record_dataset(config, args.out, progress=not args.quiet, overwrite=args.overwrite)
    seconds = time.perf_counter() - t0
    from imac_data.aloha_hdf5 import probe_episode
    import h5py

    frames = sum(probe_episode(p)["num_frames"] for p in paths)
    successes = 0
    for p in paths:
        with h5py.File(p, "r") as f:
            successes += bool(f.attrs.get("success", False))
    print(
        f"{config.task}: {len(paths)} episodes, {successes} successes, {frames} frames "
        f"({config.height}x{config.width}, {config.fps:g} fps) in {seconds:.1f} s -> {args.out}"
    )
    return 0


if __name__ == "__main__":
    from imac_data.cli import exit_process

    exit_process(main())
