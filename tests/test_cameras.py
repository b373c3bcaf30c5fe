"""Camera model against MuJoCo (the oracle) and analytic cases."""

import json

import mujoco
import numpy as np
import pytest
import torch
from dm_control.mujoco.engine import Camera as DmCamera
from dm_control.mujoco.engine import Physics

from imac_data.core.cameras import (
    Camera,
    backproject,
    load_calibration,
    project,
    rescale_intrinsics,
    save_calibration,
)
from imac_data.core.robot import aloha
from imac_data.core.robot.model import RobotModel
from imac_data.errors import InputError
from imac_data.sources.sim import rig as sim_rig


@pytest.fixture(scope="module")
def rig():
    model = sim_rig.load_mujoco_model("transfer_cube")
    robot = RobotModel(aloha.robot_config())
    return model, robot


def random_qpos(model, rng, n):
    """n random robot configurations within joint limits (MuJoCo's 16 robot joints)."""
    lo, hi = model.jnt_range[:16, 0], model.jnt_range[:16, 1]
    q = rng.uniform(lo, hi, size=(n, 16))
    q[:, 7] = -q[:, 6]  # right finger mirrors left, as gym-aloha commands it
    q[:, 15] = -q[:, 14]
    return q


def dataset_vector(qpos16: np.ndarray) -> np.ndarray:
    """MuJoCo's 16 robot joints -> gym-aloha's 14-D vector (normalised grippers)."""
    left, right = qpos16[..., :8], qpos16[..., 8:16]
    return np.concatenate([left[..., :6], aloha.normalize_gripper(left[..., 6:7]),
                           right[..., :6], aloha.normalize_gripper(right[..., 6:7])], axis=-1)


def mujoco_camera_pose_cv(data, cam_id):
    T = np.eye(4)
    T[:3, :3] = data.cam_xmat[cam_id].reshape(3, 3) @ np.diag([1.0, -1.0, -1.0])
    T[:3, 3] = data.cam_xpos[cam_id]
    return T


@pytest.mark.parametrize("task", aloha.TASKS)
def test_wrist_camera_pose_from_fk_matches_mujoco(task):
    model = sim_rig.load_mujoco_model(task)
    robot = RobotModel(aloha.robot_config())
    calib = sim_rig.camera_calibration(model, 320, 240)
    data = mujoco.MjData(model)
    qs = random_qpos(model, np.random.default_rng(0), 64)
    links = robot.link_poses(torch.as_tensor(dataset_vector(qs), dtype=torch.float64))
    worst_p = worst_r = 0.0
    for i, q in enumerate(qs):
        data.qpos[:16] = q
        mujoco.mj_kinematics(model, data)
        mujoco.mj_camlight(model, data)
        for mj_name, name in sim_rig.CAMERA_NAMES.items():
            cam_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, mj_name)
            T_ref = mujoco_camera_pose_cv(data, cam_id)
            T = calib[name].pose({k: v[i] for k, v in links.items()}, dtype=torch.float64).numpy()
            worst_p = max(worst_p, np.abs(T[:3, 3] - T_ref[:3, 3]).max())
            R_err = T[:3, :3].T @ T_ref[:3, :3]
            worst_r = max(worst_r, np.arccos(np.clip((np.trace(R_err) - 1) / 2, -1, 1)))
    assert worst_p < 1e-5, worst_p
    assert worst_r < 1e-5, worst_r


@pytest.mark.parametrize("hw", [(240, 320), (480, 640), (120, 200)])
def test_projection_matches_mujoco_camera_matrix(rig, hw):
    """A robot point projected with our cameras lands within 0.5 px of MuJoCo's projection
    (dm_control's camera matrix, built from MuJoCo's own camera state)."""
    model, robot = rig
    H, W = hw
    physics = physics_of(model)
    calib = sim_rig.camera_calibration(model, W, H)
    rng = np.random.default_rng(1)
    qs = random_qpos(model, rng, 8)
    links = robot.link_poses(torch.as_tensor(dataset_vector(qs), dtype=torch.float64))
    worst = 0.0
    n_checked = 0
    for i, q in enumerate(qs):
        physics.data.qpos[:16] = q
        physics.forward()
        # robot points: every 40th vertex of every robot mesh, posed by MuJoCo
        pts = robot_surface_points(model, physics.data)
        for mj_name, name in sim_rig.CAMERA_NAMES.items():
            M = DmCamera(physics, height=H, width=W, camera_id=mj_name).matrix
            hom = np.c_[pts, np.ones(len(pts))] @ M.T
            in_front = hom[:, 2] < -1e-3  # dm_control keeps OpenGL's sign: w < 0 in front
            uv_ref = hom[in_front, :2] / hom[in_front, 2:3]
            cam = calib[name]
            T = cam.pose({k: v[i] for k, v in links.items()}, dtype=torch.float64)
            uv, z = project(torch.as_tensor(pts[in_front]), torch.as_tensor(cam.K), T)
            visible = (uv_ref[:, 0] > -0.5) & (uv_ref[:, 0] < W - 0.5) & (uv_ref[:, 1] > -0.5) & (uv_ref[:, 1] < H - 0.5)
            err = np.abs(uv.numpy() - uv_ref)[visible]
            if len(err):
                worst = max(worst, err.max())
                n_checked += len(err)
    assert n_checked > 1000
    assert worst < 0.5, worst


def robot_surface_points(model, data, stride=40):
    pts = []
    for g in range(model.ngeom):
        mesh = model.geom_dataid[g]
        if model.geom_type[g] != mujoco.mjtGeom.mjGEOM_MESH or mesh < 0:
            continue
        if not model.body(model.geom_bodyid[g]).name.startswith("vx300s"):
            continue
        start, n = model.mesh_vertadr[mesh], model.mesh_vertnum[mesh]
        v = model.mesh_vert[start:start + n:stride]
        pts.append(v @ data.geom_xmat[g].reshape(3, 3).T + data.geom_xpos[g])
    return np.concatenate(pts)


def physics_of(model):
    xml_path = str(aloha.mjcf_path("transfer_cube"))
    physics = Physics.from_xml_path(xml_path)
    # freeze the cameras exactly as our loader does (by name: ours adds a workspace camera)
    for i in range(physics.model.ncam):
        j = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, physics.model.id2name(i, "camera"))
        physics.model.cam_mode[i] = model.cam_mode[j]
        physics.model.cam_pos[i] = model.cam_pos[j]
        physics.model.cam_quat[i] = model.cam_quat[j]
    return physics


def test_rescale_intrinsics_matches_mujoco_at_new_resolution():
    """K rescaled from 240x320 to 480x640 equals the K MuJoCo's camera model gives at 480x640."""
    model = sim_rig.load_mujoco_model("transfer_cube")
    small = sim_rig.camera_calibration(model, 320, 240)
    big = sim_rig.camera_calibration(model, 640, 480)
    for name in small:
        np.testing.assert_allclose(small[name].rescaled(640, 480).K, big[name].K, atol=1e-9)
        np.testing.assert_allclose(
            rescale_intrinsics(big[name].K, (480, 640), (240, 320)), small[name].K, atol=1e-9
        )


def test_backproject_inverts_project():
    rng = np.random.default_rng(0)
    K = torch.tensor([[300.0, 0, 159.5], [0, 310.0, 119.5], [0, 0, 1]], dtype=torch.float64)
    T = torch.eye(4, dtype=torch.float64)
    angle = 0.3
    T[:3, :3] = torch.tensor([[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]])
    T[:3, 3] = torch.tensor([0.1, -0.2, 0.5])
    depth = torch.as_tensor(rng.uniform(0.2, 3.0, size=(2, 24, 32)))
    pts = backproject(depth, K, T)  # (2, 24, 32, 3)
    uv, z = project(pts.reshape(2, -1, 3), K, T)
    grid = torch.stack(torch.meshgrid(torch.arange(24.0), torch.arange(32.0), indexing="ij")[::-1], -1)
    np.testing.assert_allclose(uv.reshape(2, 24, 32, 2).numpy(), grid.expand(2, 24, 32, 2).numpy(), atol=1e-9)
    np.testing.assert_allclose(z.reshape(2, 24, 32).numpy(), depth.numpy(), atol=1e-12)


def test_backprojected_table_depth_lies_on_the_table():
    """MuJoCo's rendered depth of the top camera, lifted with our calibration, lands on the table
    plane (z = 0) wherever MuJoCo's segmentation says the table is visible."""
    model = sim_rig.load_mujoco_model("transfer_cube")
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, 0)
    mujoco.mj_forward(model, data)
    H, W = 120, 160
    calib = sim_rig.camera_calibration(model, W, H)
    with mujoco.Renderer(model, H, W) as r:
        r.update_scene(data, camera="top")
        r.enable_depth_rendering()
        depth = r.render().copy()
        r.disable_depth_rendering()
        r.enable_segmentation_rendering()
        seg = r.render()[..., 0].copy()
    table = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "table")
    mask = seg == table
    assert mask.sum() > 1000
    cam = calib["cam_high"]
    pts = backproject(torch.as_tensor(depth, dtype=torch.float64), torch.as_tensor(cam.K),
                      torch.as_tensor(cam.T_world_cam)).numpy()
    z = pts[mask][:, 2]
    # the table mesh's top surface is at z = 0 in the world
    assert np.median(np.abs(z)) < 1e-3, np.median(np.abs(z))


def test_calibration_round_trip_and_errors(tmp_path):
    model = sim_rig.load_mujoco_model("transfer_cube")
    calib = sim_rig.camera_calibration(model, 320, 240)
    path = tmp_path / "calibration.json"
    save_calibration(path, calib)
    back = load_calibration(path)
    assert set(back) == set(calib)
    for name in calib:
        np.testing.assert_allclose(back[name].K, calib[name].K)
        assert back[name].link == calib[name].link
    bad = json.loads(path.read_text())
    del bad["cameras"]["cam_high"]["K"]
    path.write_text(json.dumps(bad))
    with pytest.raises(InputError, match=r"cameras\.cam_high.*'K'"):
        load_calibration(path)
    with pytest.raises(InputError, match="not found"):
        load_calibration(tmp_path / "nope.json")
    with pytest.raises(InputError, match="shape"):
        Camera("c", np.eye(2), 10, 10, T_world_cam=np.eye(4))
    with pytest.raises(InputError, match="either"):
        Camera("c", np.eye(3), 10, 10)
