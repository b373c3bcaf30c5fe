"""Scripted policies for the gym-aloha tasks (gym-aloha ships none).

End-effector waypoints (approach, descend, grasp, lift, meet, hand over / insert) are
computed from the objects' initial poses, interpolated with a minimum-jerk profile and
slerp, and turned into joint targets by damped-least-squares IK on the joint-position
model's own Jacobians. ``noise`` in [0, 1] degrades the policy: perception errors,
meeting-point errors, slowly varying joint-target noise and tempo jitter
(``docs/simulation.md`` has the measured success rates).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from imac_data.core.mujoco_gl import mujoco
from imac_data.core.robot.aloha import ARM_JOINTS, ARMS, normalize_gripper
from imac_data.errors import InputError
from imac_data.sources.sim.rig import CONTROL_DT
from imac_data.sources.sim.tasks import REST_HEIGHT, TABLE_Z, TASKS, TaskLayout

__all__ = ["ScriptedPolicy", "ArmIK", "Waypoint", "Trajectory", "TCP_OFFSET", "PICK_PITCH", "home_rotations",
           "lift_waypoints", "rot_x", "rot_y", "rot_z"]

# Tool centre point in the gripper_link frame: between the finger pads, 2.4 cm
# behind the finger tips (which reach x = 0.154). All waypoints target this point.
TCP_OFFSET = np.array([0.13, 0.0, 0.0])


def _quat_from_mat(R: np.ndarray) -> np.ndarray:
    q = np.empty(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(R, dtype=np.float64).ravel())
    return q


def rot_x(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def rot_y(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def rot_z(deg: float) -> np.ndarray:
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


class ArmIK:
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
class Waypoint:
    t: float  # seconds
    pos: np.ndarray  # TCP position (world)
    R: np.ndarray  # gripper_link rotation (world)
    grip: float  # normalised gripper command


class Trajectory:
    def __init__(self, waypoints: list[Waypoint]):
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


def home_rotations() -> dict[str, np.ndarray]:
    # Level grippers pointing at the centre of the table (+x for the left arm,
    # -x for the right arm, whose base is turned 180 degrees about z).
    return {"vx300s_left": np.eye(3), "vx300s_right": rot_z(180.0)}


def _transfer_cube_script(objects: dict[str, np.ndarray], home: dict, rng: np.random.Generator,
                          noise: float) -> dict[str, list[Waypoint]]:
    """Right arm picks the cube, brings it to the meeting point; left arm takes it."""
    H = home_rotations()
    pick_R = H["vx300s_right"] @ rot_y(60.0)  # pitched 60 degrees down
    meet_left_R = H["vx300s_left"] @ rot_x(90.0)  # rolled: fingers close vertically
    cube = objects["box"] + rng.normal(0.0, 0.012 * noise, 3) * np.array([1.0, 1.0, 0.3])
    meet = np.array([0.0, 0.5, 0.25])
    meet_r = meet + rng.normal(0.0, 0.008 * noise, 3)
    meet_l = meet + rng.normal(0.0, 0.008 * noise, 3)
    grasp_z = max(cube[2], TABLE_Z + 0.02)
    g0 = home["grip"]
    right = [
        Waypoint(0.0, home["vx300s_right"][0], home["vx300s_right"][1], g0),
        Waypoint(1.0, np.array([cube[0], cube[1], grasp_z + 0.08]), pick_R, 1.0),  # approach
        Waypoint(1.5, np.array([cube[0], cube[1], grasp_z]), pick_R, 1.0),  # descend
        Waypoint(1.9, np.array([cube[0], cube[1], grasp_z]), pick_R, 0.0),  # close
        Waypoint(2.1, np.array([cube[0], cube[1], grasp_z]), pick_R, 0.0),  # squeeze
        Waypoint(2.7, meet_r + np.array([0.05, 0.0, 0.0]), pick_R, 0.0),  # lift, approach meet
        Waypoint(3.0, meet_r, pick_R, 0.0),  # meet
        Waypoint(3.9, meet_r, pick_R, 0.0),  # hold while the left arm grasps
        Waypoint(4.2, meet_r, pick_R, 1.0),  # open
        Waypoint(4.6, meet_r + np.array([0.1, 0.0, 0.0]), pick_R, 1.0),  # retreat
        Waypoint(5.0, meet_r + np.array([0.1, 0.0, 0.0]), pick_R, 1.0),
    ]
    left = [
        Waypoint(0.0, home["vx300s_left"][0], home["vx300s_left"][1], g0),
        Waypoint(1.6, meet_l + np.array([-0.12, 0.0, 0.0]), meet_left_R, 1.0),  # approach meet
        Waypoint(3.0, meet_l + np.array([-0.12, 0.0, 0.0]), meet_left_R, 1.0),
        Waypoint(3.4, meet_l + np.array([0.0, 0.0, 0.0]), meet_left_R, 1.0),  # move in
        Waypoint(3.8, meet_l + np.array([0.0, 0.0, 0.0]), meet_left_R, 0.0),  # close
        Waypoint(4.2, meet_l + np.array([0.0, 0.0, 0.0]), meet_left_R, 0.0),  # hold while right opens
        Waypoint(4.7, meet_l + np.array([-0.1, 0.0, 0.02]), meet_left_R, 0.0),  # take it away
        Waypoint(5.0, meet_l + np.array([-0.1, 0.0, 0.02]), meet_left_R, 0.0),
    ]
    return {"vx300s_left": left, "vx300s_right": right}


PICK_PITCH = 60.0  # degrees the right gripper pitches down to pick the cube


def lift_waypoints(cube: np.ndarray, home: tuple[np.ndarray, np.ndarray], grip0: float,
                   lift: float = 0.10) -> list[Waypoint]:
    """The right arm's pick of the cube at ``cube`` (its centre, resting) and lift by ``lift``
    metres: the right-arm waypoints of the transfer script up to the lift, held to the end."""
    pick_R = home_rotations()["vx300s_right"] @ rot_y(PICK_PITCH)
    grasp_z = max(float(cube[2]), TABLE_Z + 0.02)
    at = np.array([cube[0], cube[1], grasp_z])
    return [
        Waypoint(0.0, home[0], home[1], grip0),
        Waypoint(1.0, at + [0.0, 0.0, 0.08], pick_R, 1.0),  # approach
        Waypoint(1.5, at, pick_R, 1.0),  # descend
        Waypoint(1.9, at, pick_R, 0.0),  # close
        Waypoint(2.1, at, pick_R, 0.0),  # squeeze
        Waypoint(2.7, at + [0.0, 0.0, lift], pick_R, 0.0),  # lift
        Waypoint(LIFT_DURATION, at + [0.0, 0.0, lift], pick_R, 0.0),  # hold
    ]


LIFT_DURATION = 3.3  # seconds: 33 frames at 10 fps, a reference frame and four chunks of 8


def _lift_script(objects: dict[str, np.ndarray], home: dict, rng: np.random.Generator,
                 noise: float) -> dict[str, list[Waypoint]]:
    """The right arm picks the cube and lifts it; the left arm stays home."""
    cube = objects["box"] + rng.normal(0.0, 0.012 * noise, 3) * np.array([1.0, 1.0, 0.3])
    left = home["vx300s_left"]
    return {"vx300s_right": lift_waypoints(cube, home["vx300s_right"], home["grip"]),
            "vx300s_left": [Waypoint(0.0, left[0], left[1], home["grip"]),
                            Waypoint(LIFT_DURATION, left[0], left[1], home["grip"])]}


def _insertion_script(objects: dict[str, np.ndarray], home: dict, rng: np.random.Generator,
                      noise: float) -> dict[str, list[Waypoint]]:
    """Right arm picks the peg, left arm the socket; they meet and the peg goes in."""
    H = home_rotations()
    pick_R = {arm: H[arm] @ rot_y(60.0) for arm in ARMS}
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
        Waypoint(0.0, home["vx300s_right"][0], home["vx300s_right"][1], g0),
        Waypoint(1.2, np.array([peg[0], peg[1], peg_z + 0.08]), pick_R["vx300s_right"], 1.0),
        Waypoint(1.7, np.array([peg[0], peg[1], peg_z]), pick_R["vx300s_right"], 1.0),
        Waypoint(2.1, np.array([peg[0], peg[1], peg_z]), pick_R["vx300s_right"], 0.0),
        Waypoint(2.3, np.array([peg[0], peg[1], peg_z]), pick_R["vx300s_right"], 0.0),
        Waypoint(3.2, r_in + np.array([0.06, 0.0, 0.0]), pick_R["vx300s_right"], 0.0),
        Waypoint(4.2, r_in + np.array([-0.015, 0.0, 0.0]), pick_R["vx300s_right"], 0.0),
        Waypoint(4.6, r_in + np.array([-0.015, 0.0, 0.0]), pick_R["vx300s_right"], 0.0),
    ]
    left = [
        Waypoint(0.0, home["vx300s_left"][0], home["vx300s_left"][1], g0),
        Waypoint(1.2, np.array([socket[0], socket[1], socket_z + 0.08]), pick_R["vx300s_left"], 1.0),
        Waypoint(1.7, np.array([socket[0], socket[1], socket_z]), pick_R["vx300s_left"], 1.0),
        Waypoint(2.1, np.array([socket[0], socket[1], socket_z]), pick_R["vx300s_left"], 0.0),
        Waypoint(2.3, np.array([socket[0], socket[1], socket_z]), pick_R["vx300s_left"], 0.0),
        Waypoint(3.2, l_in + np.array([-0.06, 0.0, 0.0]), pick_R["vx300s_left"], 0.0),
        Waypoint(4.2, l_in, pick_R["vx300s_left"], 0.0),
        Waypoint(4.6, l_in, pick_R["vx300s_left"], 0.0),
    ]
    return {"vx300s_left": left, "vx300s_right": right}


_SCRIPTS = {"transfer_cube": _transfer_cube_script, "insertion": _insertion_script, "lift": _lift_script}


class ScriptedPolicy:
    """Open-loop waypoint policy for one episode; ``policy(t)`` returns the 14-D action
    (joint-position targets + normalised gripper commands) at time ``t`` seconds."""

    def __init__(self, task: str, model: mujoco.MjModel, data: mujoco.MjData,
                 rng: np.random.Generator, noise: float = 0.0):
        if task not in TASKS:
            raise InputError(f"unknown task {task!r}; expected one of {TASKS}")
        self.layout = layout = TaskLayout(model, task)
        self.noise = float(noise)
        self.rng = rng
        self.ik = {arm: ArmIK(model, arm) for arm in ARMS}
        self.q = {arm: data.qpos[self.ik[arm].qadr].copy() for arm in ARMS}
        home = {arm: self.ik[arm].fk(self.q[arm]) for arm in ARMS}
        home["grip"] = float(normalize_gripper(data.qpos[layout.finger_qadr[0]]))
        # Objects spawn above the table and drop straight down: plan for their resting height.
        objects = {}
        for name, bid in layout.object_bodies.items():
            objects[name] = data.xpos[bid].copy()
            objects[name][2] = TABLE_Z + REST_HEIGHT[name]
        scripts = _SCRIPTS[task](objects, home, rng, self.noise)
        # Tempo jitter: a noisy operator is not uniformly paced.
        self.tempo = 1.0 + self.noise * rng.uniform(-0.1, 0.1)
        self.traj = {arm: Trajectory(wps) for arm, wps in scripts.items()}
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
