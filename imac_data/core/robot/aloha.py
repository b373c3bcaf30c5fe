"""The ALOHA platform: gym-aloha's two ViperX 300s as a robot description and a controller.

Everything comes from the installed ``gym_aloha`` package at run time: the URDF is exported
from its MJCF (meshes referenced, never copied) and the controller's clipping from its
position actuators. The simulated rig (cameras, physics) is :mod:`imac_data.sources.sim.rig`.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
from gym_aloha.constants import ASSETS_DIR as ALOHA_ASSETS
from gym_aloha.constants import PUPPET_GRIPPER_POSITION_CLOSE as GRIPPER_CLOSE
from gym_aloha.constants import PUPPET_GRIPPER_POSITION_OPEN as GRIPPER_OPEN

from imac_data.core.motion import Controller, GripperActionMap
from imac_data.core.mujoco_gl import mujoco
from imac_data.core.robot import mjcf
from imac_data.core.robot.model import GripperMap, RobotConfig
from imac_data.errors import InputError
from imac_data.layout import cache_home

__all__ = ["TASKS", "SCENE_OF_TASK", "SIM_TASKS", "ARM_JOINTS", "ARMS", "STATE_NAMES", "GRIPPER_CLOSE", "GRIPPER_OPEN", "mjcf_path",
           "normalize_gripper", "unnormalize_gripper", "robot_config", "controller"]

TASKS = ("transfer_cube", "insertion")  # gym-aloha's scenes (one MJCF each)
SCENE_OF_TASK = {"lift": "transfer_cube"}  # our tasks that reuse a gym-aloha scene
SIM_TASKS = TASKS + tuple(SCENE_OF_TASK)  # what the simulator records
ARM_JOINTS = ("waist", "shoulder", "elbow", "forearm_roll", "wrist_angle", "wrist_rotate")
ARMS = ("vx300s_left", "vx300s_right")

# The 14-D qpos/action vector of gym-aloha (and of ALOHA / AgileX HDF5 episodes).
STATE_NAMES = tuple(
    f"{side}_{name}"
    for side in ("left", "right")
    for name in (*[f"arm_{j}" for j in ARM_JOINTS], "gripper")
)


def normalize_gripper(finger_position):
    """Finger slide position (m) -> gym-aloha's normalised gripper value (0 closed, 1 open)."""
    return (finger_position - GRIPPER_CLOSE) / (GRIPPER_OPEN - GRIPPER_CLOSE)


def unnormalize_gripper(value):
    """Normalised gripper value -> ``left_finger`` slide position in metres."""
    return GRIPPER_CLOSE + value * (GRIPPER_OPEN - GRIPPER_CLOSE)


def mjcf_path(task: str, end_effector: bool = False) -> Path:
    """gym-aloha's MJCF of ``task``'s scene."""
    task = SCENE_OF_TASK.get(task, task)
    if task not in TASKS:
        raise InputError(f"unknown ALOHA task {task!r}; expected one of {SIM_TASKS}")
    kind = "end_effector_" if end_effector else ""
    return Path(ALOHA_ASSETS) / f"bimanual_viperx_{kind}{task}.xml"


def robot_config(cache_dir: str | Path | None = None) -> RobotConfig:
    """The two ViperX 300s, driven by gym-aloha's 14-D vector.

    The URDF is exported into ``cache_dir`` (default ``~/.cache/imac/aloha``) under a name
    that hashes everything the export depends on, so an unchanged setup skips the export.
    """
    pkg_dir = Path(ALOHA_ASSETS).resolve().parent  # the gym_aloha package: package://gym_aloha/
    mimic = {f"{arm}/right_finger": (f"{arm}/left_finger", -1.0, 0.0) for arm in ARMS}

    h = hashlib.sha256()
    h.update(f"mujoco {mujoco.__version__}; roots {ARMS}; mimic {sorted(mimic.items())}".encode())
    h.update(Path(mjcf.__file__).read_bytes())
    for f in sorted(Path(ALOHA_ASSETS).iterdir()):
        if f.is_file():
            h.update(f.name.encode() + b"\0" + f.read_bytes())
    cache_dir = Path(cache_dir) if cache_dir is not None else cache_home() / "aloha"
    urdf_path = cache_dir / f"aloha_{h.hexdigest()[:16]}.urdf"
    if not urdf_path.is_file():
        # The robot subtrees are identical in every task's MJCF; only the props differ.
        model = mujoco.MjModel.from_xml_path(str(mjcf_path("transfer_cube")))
        mjcf.write_urdf(urdf_path, model, ARMS, mesh_dir=ALOHA_ASSETS, mimic=mimic, robot_name="aloha",
                        mesh_uri=lambda p: f"package://gym_aloha/{p.relative_to(pkg_dir).as_posix()}")

    joint_map = []
    for arm in ARMS:
        joint_map += [f"{arm}/{j}" for j in ARM_JOINTS]
        # normalised gripper (0 closed, 1 open) -> left finger slide; right finger mimics it (x -1)
        joint_map.append(GripperMap(len(joint_map), f"{arm}/left_finger",
                                    scale=GRIPPER_OPEN - GRIPPER_CLOSE, offset=GRIPPER_CLOSE))
    # The finger links carry the pads that grasp, so scene-to-gripper measures distance to the
    # grasping surfaces; the housing (with the wrist camera mount) is part of the robot stream anyway.
    gripper_links = tuple(f"{arm}/{side}_finger_link" for arm in ARMS for side in ("left", "right"))
    return RobotConfig(name="aloha", urdf_path=urdf_path, joint_map=tuple(joint_map),
                       gripper_links=gripper_links, package_dirs={"gym_aloha": pkg_dir})


def controller(task: str | None = None, dof: int = 14) -> Controller:
    """Absolute joint-position targets, gripper actions in the state's normalised units (0
    closed, 1 open: identity map). With a ``task``, the targets also saturate as that task's
    position actuators saturate their ``ctrl`` (the fingers: [0.021, 0.057] m, normalised
    [0.065, 0.974]): a commanded 0 leaves the fingers at their joint limit, not beyond it."""
    if dof != 14:
        raise InputError(f"the ALOHA controller drives 14 joints, got dof={dof}")
    if task is None:
        return Controller(mode="absolute", grippers=(GripperActionMap(6), GripperActionMap(13)))
    model = mujoco.MjModel.from_xml_path(str(mjcf_path(task)))
    low, high = np.full(dof, -np.inf), np.full(dof, np.inf)
    for k, arm in enumerate(ARMS):
        for i, joint in enumerate((*ARM_JOINTS, "left_finger")):
            jid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, f"{arm}/{joint}")
            act = np.flatnonzero((model.actuator_trntype == mujoco.mjtTrn.mjTRN_JOINT)
                                 & (model.actuator_trnid[:, 0] == jid))
            if jid < 0 or len(act) != 1:
                raise InputError(f"MuJoCo model has no single position actuator on joint {arm}/{joint}")
            if not model.actuator_ctrllimited[act[0]]:
                continue
            lo, hi = model.actuator_ctrlrange[act[0]]
            if joint == "left_finger":
                lo, hi = normalize_gripper(lo), normalize_gripper(hi)
            low[7 * k + i], high[7 * k + i] = lo, hi
    grippers = [GripperActionMap(i, low=float(low[i]), high=float(high[i])) for i in (6, 13)]
    return Controller(mode="absolute", grippers=tuple(grippers),
                      clip_low=tuple(float(x) for x in low), clip_high=tuple(float(x) for x in high))
