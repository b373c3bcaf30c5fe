"""The gym-aloha tasks as the simulator sees them: where the objects and fingers are, the
staged reward, and the success label read off the final simulator state (never from a
script's intent)."""

from __future__ import annotations

import math

import numpy as np

from imac_data.core.mujoco_gl import mujoco
from imac_data.core.robot.aloha import (
    ARM_JOINTS,
    ARMS,
    GRIPPER_CLOSE,
    GRIPPER_OPEN,
    SIM_TASKS,
    normalize_gripper,
    unnormalize_gripper,
)
from imac_data.errors import InputError

__all__ = ["TASKS", "TASK_INSTRUCTIONS", "TABLE_Z", "REST_HEIGHT", "LIFT_HEIGHT", "TaskLayout",
           "task_reward", "task_success"]

TASKS = SIM_TASKS
# Instructions of LeRobot's aloha_sim datasets (lerobot/aloha_sim_*), which gym-aloha's tasks come from;
# lift is the first half of transfer_cube, the right arm alone.
TASK_INSTRUCTIONS = {
    "transfer_cube": "Pick up the cube with the right arm and transfer it to the left arm.",
    "insertion": "Insert the peg into the socket.",
    "lift": "Pick up the cube with the right arm and lift it.",
}
LIFT_HEIGHT = 0.04  # lift succeeds when the cube's bottom is at least this far above the table

TABLE_Z = 0.0  # the table top (gym-aloha's tabletop mesh spans z in [-0.03, 0])

# Height of each object's centre above the table when it rests there.
REST_HEIGHT = {"box": 0.02, "peg": 0.01, "socket": 0.022}


class TaskLayout:
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
        names = {"transfer_cube": ("box",), "lift": ("box",), "insertion": ("peg", "socket")}[task]
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




def _contact_pairs(data: mujoco.MjData) -> set[tuple[int, int]]:
    n = data.ncon
    if n == 0:
        return set()
    g1 = data.contact.geom1[:n]
    g2 = data.contact.geom2[:n]
    return {(int(a), int(b)) for a, b in zip(g1, g2)} | {(int(b), int(a)) for a, b in zip(g1, g2)}


def _touch(pairs, a: set[int], b: set[int]) -> bool:
    return any((x, y) in pairs for x in a for y in b)


def task_reward(layout: TaskLayout, data: mujoco.MjData, task: str) -> int:
    """gym-aloha's staged reward (0..4) from the current contacts, with either finger of
    a gripper counting as that gripper."""
    pairs = _contact_pairs(data)
    left, right = layout.fingers["vx300s_left"], layout.fingers["vx300s_right"]
    if task in ("transfer_cube", "lift"):  # lift reaches levels 1 and 2 at most
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


def insertion_depth(layout: TaskLayout, data: mujoco.MjData) -> float:
    """How far (m) the peg's end is inside the socket tube (negative: outside/misaligned)."""
    pb, sb = layout.object_bodies["peg"], layout.object_bodies["socket"]
    Rs = data.xmat[sb].reshape(3, 3)
    p = Rs.T @ (data.xpos[pb] - data.xpos[sb])
    axis = Rs.T @ data.xmat[pb].reshape(3, 3)[:, 0]
    if abs(p[1]) > 0.012 or abs(p[2]) > 0.012 or abs(axis[0]) < math.cos(math.radians(20)):
        return -1.0
    return 0.12 - abs(p[0])  # socket half-length 0.06 + peg half-length 0.06


def task_success(layout: TaskLayout, data: mujoco.MjData, task: str) -> bool:
    """The label, from the final simulator state.

    transfer_cube: the cube touches a left-gripper finger, no right-gripper finger and not
    the table, and its centre is at least 5 cm above the table top (held by the left arm alone).
    insertion: neither object touches the table and the peg's end is at least 1 cm inside the
    socket tube, axes aligned within 20 degrees (gym-aloha's reward only asks for a
    peg-pin touch at some instant; we want the peg to *be* in the socket at the end).
    lift: the cube touches a right-gripper finger, no left-gripper finger and not the table,
    and its bottom is at least :data:`LIFT_HEIGHT` above the table top.
    """
    pairs = _contact_pairs(data)

    def cube_held_by(arm: str, other: str) -> bool:
        return (_touch(pairs, layout.box, layout.fingers[arm]) and not _touch(pairs, layout.box, layout.fingers[other])
                and not _touch(pairs, layout.box, layout.table))

    if task in ("lift", "transfer_cube"):
        box_z = data.xpos[layout.object_bodies["box"]][2]
        if task == "lift":
            return cube_held_by("vx300s_right", "vx300s_left") and box_z >= TABLE_Z + REST_HEIGHT["box"] + LIFT_HEIGHT
        return cube_held_by("vx300s_left", "vx300s_right") and box_z > TABLE_Z + 0.05
    off_table = not (_touch(pairs, layout.peg, layout.table) or _touch(pairs, layout.socket, layout.table))
    return off_table and insertion_depth(layout, data) > 0.01
