"""The simulated ALOHA rig: gym-aloha's MuJoCo model with rigid cameras, and its calibration.

gym-aloha's cameras use ``mode="targetbody"``: MuJoCo re-derives their roll from the world's
up axis every step, so a "wrist" camera is not rigid on the wrist. Real wrist cameras are
bolted on, so :func:`load_mujoco_model` freezes every camera at its keyframe-0 pose.
"""

from __future__ import annotations

import numpy as np

from imac_data.core.cameras import Camera, intrinsics_from_fovy, opengl_to_opencv
from imac_data.core.mujoco_gl import mujoco
from imac_data.core.robot.aloha import ARM_JOINTS, ARMS, mjcf_path, unnormalize_gripper
from imac_data.errors import InputError

__all__ = ["CAMERA_NAMES", "WORKSPACE_CAMERA", "RIG_CAMERAS", "CONTROL_DT", "load_mujoco_model", "camera_calibration", "set_mujoco_qpos"]

# MuJoCo camera -> dataset camera name (ALOHA HDF5 / LeRobot convention): the three ALOHA cameras.
CAMERA_NAMES = {"top": "cam_high", "left_wrist": "cam_left_wrist", "right_wrist": "cam_right_wrist"}
# A fixed, low side camera that frames where the cube starts and where it is lifted (gym-aloha samples
# the cube over x 0-0.2 m, y 0.4-0.6 m). It looks along +x, the way the right arm reaches, so the
# gripper's fingers close across its image: a grasp's y offset, which decides the lift, shows as pixels,
# not depth; the head camera looks almost straight down, where a lift shows mostly in depth
# (docs/simulation.md, "A workspace camera").
WORKSPACE_CAMERA = {"workspace": "cam_workspace"}
WORKSPACE_POSE = {"pos": (-0.3, 0.5, 0.2), "target": (0.1, 0.5, 0.05), "fovy": 36.0}
RIG_CAMERAS = {**CAMERA_NAMES, **WORKSPACE_CAMERA}  # every camera the simulated rig can record

# Simulation rates of gym-aloha: 50 Hz control, 500 Hz physics.
CONTROL_DT = 0.02


def load_mujoco_model(task: str, end_effector: bool = False) -> mujoco.MjModel:
    """gym-aloha's model for ``task`` (lift: the cube-transfer scene) with every camera frozen to
    a rigid mount at the pose MuJoCo computes at the first keyframe (so images look as
    gym-aloha's do at the start)."""
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
    _add_workspace_camera(spec)
    return spec.compile()


def _add_workspace_camera(spec: mujoco.MjSpec) -> None:
    """The fixed workspace camera (:data:`WORKSPACE_POSE`) on the world body. A camera changes
    neither the physics nor the other cameras' images."""
    pos, target = np.array(WORKSPACE_POSE["pos"]), np.array(WORKSPACE_POSE["target"])
    forward = (target - pos) / np.linalg.norm(target - pos)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)  # MuJoCo cameras look down -z with y up
    spec.worldbody.add_camera(name=next(iter(WORKSPACE_CAMERA)), pos=pos, xyaxes=np.r_[right, up],
                              fovy=WORKSPACE_POSE["fovy"])


def camera_calibration(model: mujoco.MjModel, width: int, height: int,
                       cameras: dict[str, str] = CAMERA_NAMES) -> dict[str, Camera]:
    """Dataset camera name -> :class:`Camera`, read off a model with fixed-mode cameras
    (:func:`load_mujoco_model`). Cameras on the world body are fixed; the others are mounted
    on the URDF link of their body's name (the MJCF export keeps body names)."""
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


def set_mujoco_qpos(model: mujoco.MjModel, data: mujoco.MjData, q14) -> None:
    """Put gym-aloha's 14-D joint vector into ``data.qpos`` as gym-aloha does (left finger =
    unnormalised gripper, right finger = -left finger); other joints are left as they are."""
    for k, arm in enumerate(ARMS):
        for i, joint in enumerate(ARM_JOINTS):
            data.qpos[model.joint(f"{arm}/{joint}").qposadr[0]] = q14[7 * k + i]
        finger = unnormalize_gripper(q14[7 * k + 6])
        data.qpos[model.joint(f"{arm}/left_finger").qposadr[0]] = finger
        data.qpos[model.joint(f"{arm}/right_finger").qposadr[0]] = -finger
