"""The simulated ALOHA rig of gym-aloha: MuJoCo model, cameras and robot description.

Everything is derived at run time from the installed ``gym_aloha`` package (its
MJCF and meshes are referenced, never copied). Two deliberate changes to the
model as shipped:

* gym-aloha's cameras use ``mode="targetbody"``: MuJoCo re-derives their roll from
  the world's up axis every step, so a "wrist" camera is not rigid on the wrist.
  Real wrist cameras are bolted on, so :func:`load_mujoco_model` freezes every
  camera to ``mode="fixed"`` at the pose it has in the model's keyframe.
"""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np

from imac_data.cameras import Camera, intrinsics_from_fovy, opengl_to_opencv
from imac_data.errors import InputError

try:
    from gym_aloha.constants import ASSETS_DIR as ALOHA_ASSETS
    from gym_aloha.constants import PUPPET_GRIPPER_POSITION_CLOSE as GRIPPER_CLOSE
    from gym_aloha.constants import PUPPET_GRIPPER_POSITION_OPEN as GRIPPER_OPEN
except ImportError as e:  # pragma: no cover - gym-aloha is a hard dependency
    raise ImportError("gym-aloha is required for the simulated ALOHA rig: pip install gym-aloha") from e

TASKS = ("transfer_cube", "insertion")

ARM_JOINTS = ("waist", "shoulder", "elbow", "forearm_roll", "wrist_angle", "wrist_rotate")
ARMS = ("vx300s_left", "vx300s_right")

# The 14-D qpos/action vector of gym-aloha (and of ALOHA / AgileX HDF5 episodes).
STATE_NAMES = tuple(
    f"{side}_{name}"
    for side in ("left", "right")
    for name in (*[f"arm_{j}" for j in ARM_JOINTS], "gripper")
)

# MuJoCo camera -> dataset camera name (ALOHA HDF5 / LeRobot convention).
CAMERA_NAMES = {"top": "cam_high", "left_wrist": "cam_left_wrist", "right_wrist": "cam_right_wrist"}

# Simulation rates of gym-aloha: 50 Hz control, 500 Hz physics.
CONTROL_DT = 0.02


def normalize_gripper(finger_position):
    """Finger slide position (m) -> gym-aloha's normalised gripper value (0 closed, 1 open)."""
    return (finger_position - GRIPPER_CLOSE) / (GRIPPER_OPEN - GRIPPER_CLOSE)


def unnormalize_gripper(value):
    """Normalised gripper value -> ``left_finger`` slide position in metres."""
    return GRIPPER_CLOSE + value * (GRIPPER_OPEN - GRIPPER_CLOSE)


def mjcf_path(task: str, end_effector: bool = False) -> Path:
    if task not in TASKS:
        raise InputError(f"unknown ALOHA task {task!r}; expected one of {TASKS}")
    kind = "end_effector_" if end_effector else ""
    return Path(ALOHA_ASSETS) / f"bimanual_viperx_{kind}{task}.xml"


def load_mujoco_model(task: str, end_effector: bool = False) -> mujoco.MjModel:
    """gym-aloha's model for ``task`` with every camera frozen to a rigid mount.

    The frozen pose is the one MuJoCo computes at the model's first keyframe, so
    the images look as gym-aloha's do at the start pose.
    """
    spec = mujoco.MjSpec.from_file(str(mjcf_path(task, end_effector)))
    model = spec.compile()
    data = mujoco.MjData(model)
    if model.nkey:
        mujoco.mj_resetDataKeyframe(model, data, 0)
    mujoco.mj_forward(model, data)
    for cam_id in range(model.ncam):
        body = model.cam_bodyid[cam_id]
        R_body = data.xmat[body].reshape(3, 3)
        R_rel = R_body.T @ data.cam_xmat[cam_id].reshape(3, 3)
        p_rel = R_body.T @ (data.cam_xpos[cam_id] - data.xpos[body])
        quat = np.empty(4)
        mujoco.mju_mat2Quat(quat, R_rel.flatten())
        cam = spec.camera(model.camera(cam_id).name)
        cam.mode = mujoco.mjtCamLight.mjCAMLIGHT_FIXED
        cam.targetbody = ""
        cam.pos = p_rel
        cam.quat = quat
    return spec.compile()


def camera_calibration(model: mujoco.MjModel, width: int, height: int,
                       cameras: dict[str, str] = CAMERA_NAMES) -> dict[str, Camera]:
    """Rig calibration (dataset camera name -> :class:`Camera`) read off a MuJoCo model
    whose cameras are fixed-mode (see :func:`load_mujoco_model`).

    Cameras on the world body are *fixed*; cameras on any other body are *mounted*
    on the URDF link of the same name (our MJCF->URDF export keeps body names).
    """
    calib = {}
    for mj_name, name in cameras.items():
        cam_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, mj_name)
        if cam_id < 0:
            raise InputError(f"MuJoCo model has no camera {mj_name!r}")
        if model.cam_mode[cam_id] != mujoco.mjtCamLight.mjCAMLIGHT_FIXED:
            raise InputError(f"camera {mj_name!r} is not fixed-mode; load the model with load_mujoco_model()")
        T = np.eye(4)
        R = np.empty(9)
        mujoco.mju_quat2Mat(R, model.cam_quat[cam_id])
        T[:3, :3] = R.reshape(3, 3)
        T[:3, 3] = model.cam_pos[cam_id]
        T = opengl_to_opencv(T)
        K = intrinsics_from_fovy(float(model.cam_fovy[cam_id]), width, height)
        body = model.cam_bodyid[cam_id]
        if body == 0:
            calib[name] = Camera(name, K, width, height, T_world_cam=T)
        else:
            calib[name] = Camera(name, K, width, height, link=model.body(body).name, T_link_cam=T)
    return calib


# ----------------------------------------------------------------------------- robot description

def robot_config(cache_dir: str | Path | None = None):
    """:class:`~imac_data.robot.RobotConfig` of the two ViperX 300s, driven by gym-aloha's 14-D vector.

    The URDF is exported at run time from gym-aloha's own MJCF (meshes referenced
    as ``package://gym_aloha/...``, never copied) into ``cache_dir`` (default
    ``$XDG_CACHE_HOME/imac/aloha``, i.e. ``~/.cache/imac/aloha``). The file name
    carries a hash of everything the export depends on (gym-aloha's assets, the
    exporter's source, the MuJoCo version), so an unchanged setup skips the export.
    """
    import hashlib
    import os

    import imac_data.mjcf_to_urdf as m2u
    from imac_data.robot import GripperMap, RobotConfig

    pkg_dir = Path(ALOHA_ASSETS).resolve().parent  # the gym_aloha package: package://gym_aloha/
    mimic = {f"{arm}/right_finger": (f"{arm}/left_finger", -1.0, 0.0) for arm in ARMS}

    h = hashlib.sha256()
    h.update(f"mujoco {mujoco.__version__}; roots {ARMS}; mimic {sorted(mimic.items())}".encode())
    h.update(Path(m2u.__file__).read_bytes())
    for f in sorted(Path(ALOHA_ASSETS).iterdir()):
        if f.is_file():
            h.update(f.name.encode() + b"\0" + f.read_bytes())
    if cache_dir is None:
        cache_dir = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "imac" / "aloha"
    urdf_path = Path(cache_dir) / f"aloha_{h.hexdigest()[:16]}.urdf"
    if not urdf_path.is_file():
        # The robot subtrees are identical in every task's MJCF; only the props differ.
        model = mujoco.MjModel.from_xml_path(str(mjcf_path("transfer_cube")))
        m2u.write_urdf(urdf_path, model, ARMS, mesh_dir=ALOHA_ASSETS, mimic=mimic, robot_name="aloha",
                       mesh_uri=lambda p: f"package://gym_aloha/{p.relative_to(pkg_dir).as_posix()}")

    joint_map = []
    for arm in ARMS:
        joint_map += [f"{arm}/{j}" for j in ARM_JOINTS]
        # normalised gripper (0 closed, 1 open) -> left finger slide; right finger mimics it (x -1)
        joint_map.append(GripperMap(len(joint_map), f"{arm}/left_finger",
                                    scale=GRIPPER_OPEN - GRIPPER_CLOSE, offset=GRIPPER_CLOSE))
    # Gripper = the two finger links only: they carry the pads that grasp, so the
    # scene->gripper stream measures distance to the grasping surfaces. The housing
    # (gripper_link, with the wrist camera mount) is part of the robot stream anyway.
    gripper_links = tuple(f"{arm}/{side}_finger_link" for arm in ARMS for side in ("left", "right"))
    return RobotConfig(name="aloha", urdf_path=urdf_path, joint_map=tuple(joint_map),
                       gripper_links=gripper_links, package_dirs={"gym_aloha": pkg_dir})


def set_mujoco_qpos(model: mujoco.MjModel, data: mujoco.MjData, q14) -> None:
    """Put gym-aloha's 14-D joint vector into ``data.qpos`` the way gym-aloha does
    (left finger = unnormalised gripper, right finger = -left finger); other joints
    are left as they are."""
    for k, arm in enumerate(ARMS):
        for i, joint in enumerate(ARM_JOINTS):
            data.qpos[model.joint(f"{arm}/{joint}").qposadr[0]] = q14[7 * k + i]
        finger = unnormalize_gripper(q14[7 * k + 6])
        data.qpos[model.joint(f"{arm}/left_finger").qposadr[0]] = finger
        data.qpos[model.joint(f"{arm}/right_finger").qposadr[0]] = -finger
