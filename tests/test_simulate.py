"""The simulated recorder (imac_data.sources.sim.recorder) against independent oracles: the HDF5
reader, the analytic table plane (depth), camera projection of known world points
(segmentation), and the simulator's own contacts (success labels)."""

from __future__ import annotations

import math

import h5py
import mujoco
import numpy as np
import pytest
import torch
from gym_aloha.utils import sample_box_pose

from imac_data.cli import main as imac_main
from imac_data.core.cameras import load_calibration, project
from imac_data.core.robot.aloha import STATE_NAMES
from imac_data.errors import InputError
from imac_data.sources.hdf5 import probe_episode, read_episode
from imac_data.sources.sim.env import FrameRenderer, SimEnv, robot_mask, segmentation_labels
from imac_data.sources.sim.recorder import SimConfig, record_dataset, simulate_episode
from imac_data.sources.sim.rig import CAMERA_NAMES, CONTROL_DT, load_mujoco_model
from imac_data.sources.sim.tasks import TASK_INSTRUCTIONS

CAMS = sorted(CAMERA_NAMES.values())


@pytest.fixture(scope="module")
def cube_dir(tmp_path_factory):
    """Two frames of transfer_cube at the default 240x320, with segmentation."""
    out = tmp_path_factory.mktemp("sim_cube")
    cfg = SimConfig(task="transfer_cube", num_episodes=1, seed=3, max_steps=4, with_segmentation=True)
    paths = record_dataset(cfg, out, progress=False)
    return out, paths, cfg


@pytest.fixture(scope="module")
def insertion_dir(tmp_path_factory):
    """Three frames of insertion at 50 fps, 120x160, JPEG-compressed RGB."""
    out = tmp_path_factory.mktemp("sim_insertion")
    cfg = SimConfig(task="insertion", num_episodes=2, seed=5, width=160, height=120, frame_stride=1,
                    max_steps=3, compress=True)
    paths = record_dataset(cfg, out, progress=False)
    return out, paths, cfg


# --------------------------------------------------------------------------- format


@pytest.mark.parametrize("which", ["cube_dir", "insertion_dir"])
def test_recorded_episode_reads_back(which, request):
    out, paths, cfg = request.getfixturevalue(which)
    assert [p.name for p in paths] == [f"episode_{i}.hdf5" for i in range(cfg.num_episodes)]
    assert not list(out.glob(".*tmp*")), "temporary files left behind"
    T = cfg.max_steps // cfg.frame_stride
    for i, path in enumerate(paths):
        ep = read_episode(path, load_segmentation=True)
        assert (ep.info.sim_task, ep.info.sim_seed) == (cfg.task, cfg.seed + i)
        assert ep.cameras == CAMS
        assert ep.num_frames == T
        for arr in (ep.qpos, ep.qvel, ep.action):
            assert arr.shape == (T, len(STATE_NAMES)) and np.isfinite(arr).all()
        for cam in CAMS:
            assert ep.images[cam].shape == (T, cfg.height, cfg.width, 3) and ep.images[cam].dtype == np.uint8
            assert ep.depth_mm[cam].shape == (T, cfg.height, cfg.width) and ep.depth_mm[cam].dtype == np.uint16
            assert ep.images[cam].std() > 5  # something was rendered
        if cfg.with_segmentation:
            for cam in CAMS:
                seg = ep.segmentation[cam]
                assert seg.shape == (T, cfg.height, cfg.width) and seg.dtype == np.int16
                assert set(np.unique(seg)) <= set(ep.segmentation_labels) | {-1}
                # Nothing hit <=> invalid depth (the scene has no background geometry).
                np.testing.assert_array_equal(seg == -1, ep.depth_mm[cam] == 0)
        else:
            assert ep.segmentation == {}
        assert ep.fps == pytest.approx(cfg.fps) == pytest.approx(50.0 / cfg.frame_stride)
        assert ep.info.task == TASK_INSTRUCTIONS[cfg.task]
        assert ep.info.source == "policy" and ep.info.policy_name == f"scripted_{cfg.task}"
        assert isinstance(ep.info.success, bool)
        # Grippers are normalised (0 closed .. 1 open); the start pose is gym-aloha's.
        assert np.all((ep.action[:, [6, 13]] >= 0) & (ep.action[:, [6, 13]] <= 1))
        np.testing.assert_allclose(ep.qpos[0, [1, 2, 4]], [-0.96, 1.16, -0.3], atol=1e-9)
    with h5py.File(paths[0], "r") as f:
        assert bool(f.attrs["compress"]) == cfg.compress
    calib = load_calibration(out / "calibration.json")
    assert sorted(calib) == CAMS
    assert all((c.width, c.height) == (cfg.width, cfg.height) for c in calib.values())
    assert not calib["cam_high"].is_mounted and calib["cam_left_wrist"].link == "vx300s_left/gripper_link"


# --------------------------------------------------------------------------- geometry


def _pixel_rays(K: np.ndarray, T_world_cam: np.ndarray, v: np.ndarray, u: np.ndarray):
    rays_cam = np.stack([u, v, np.ones_like(u)], -1).astype(np.float64) @ np.linalg.inv(K).T  # z == 1
    return T_world_cam[:3, 3], rays_cam @ T_world_cam[:3, :3].T, rays_cam


def _check_table_depth(depth_mm, seg, table_id, K, T_world_cam, min_pixels):
    mask = seg == table_id
    # Stay off silhouette edges: keep table pixels whose 4-neighbours are table too.
    inner = mask.copy()
    inner[1:-1, 1:-1] &= mask[:-2, 1:-1] & mask[2:, 1:-1] & mask[1:-1, :-2] & mask[1:-1, 2:]
    inner[[0, -1], :] = False
    inner[:, [0, -1]] = False
    v, u = np.nonzero(inner)
    assert len(v) >= min_pixels
    centre, rays_world, rays_cam = _pixel_rays(K, T_world_cam, v, u)
    s = (0.0 - centre[2]) / rays_world[:, 2]  # table top is the plane z = 0
    z_depth_mm = 1000.0 * s  # the rays have unit camera z, so s is the planar depth
    ray_dist_mm = z_depth_mm * np.linalg.norm(rays_cam, axis=1)
    recorded = depth_mm[v, u].astype(np.float64)
    assert np.abs(recorded - z_depth_mm).max() <= 1.0
    # ...and the test can tell z-depth from ray distance.
    assert np.abs(recorded - ray_dist_mm).max() > 20.0


@pytest.mark.parametrize("which", ["cube_dir", "insertion_dir"])
def test_recorded_episodes_re_simulate_from_their_own_files(which, request):
    """The start seed and task in the file's attributes, the rate from its fps and its actions:
    MuJoCo retraces the recorded joints bit for bit."""
    _, paths, _ = request.getfixturevalue(which)
    for path in paths:
        ep = read_episode(path, load_depth=False)
        env = SimEnv(ep.info.sim_task, frame_stride=round(1 / (ep.fps * CONTROL_DT)))
        env.reset(ep.info.sim_seed)
        qpos = []
        for action in ep.action:
            qpos.append(env.qpos())
            env.step(action)
        np.testing.assert_array_equal(np.array(qpos), ep.qpos)


def test_depth_is_planar_z_depth_of_the_table(cube_dir):
    out, paths, _ = cube_dir
    ep = read_episode(paths[0], load_segmentation=True)
    calib = load_calibration(out / "calibration.json")
    table = next(g for g, (name, _) in ep.segmentation_labels.items() if name == "table")
    cam = calib["cam_high"]
    _check_table_depth(ep.depth_mm["cam_high"][0], ep.segmentation["cam_high"][0], table, cam.K,
                       cam.T_world_cam, min_pixels=5000)


def test_wrist_depth_matches_mounted_calibration(cube_dir):
    """A mounted camera: its pose is link pose (from MuJoCo) @ the saved T_link_cam."""
    out, _, _ = cube_dir
    calib = load_calibration(out / "calibration.json")
    model = load_mujoco_model("transfer_cube")
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, 0)
    mujoco.mj_forward(model, data)
    cam = calib["cam_left_wrist"]
    with FrameRenderer(model, cam.width, cam.height, segmentation=True) as renderer:
        frame = renderer.render(data)
    body = model.body(cam.link).id
    T_world_link = np.eye(4)
    T_world_link[:3, :3] = data.xmat[body].reshape(3, 3)
    T_world_link[:3, 3] = data.xpos[body]
    table = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "table")
    _check_table_depth(frame["depth_mm"]["cam_left_wrist"], frame["segmentation"]["cam_left_wrist"], table,
                       cam.K, T_world_link @ cam.T_link_cam, min_pixels=2000)


def test_cube_projects_where_the_calibration_says(cube_dir):
    """The cube's segmentation in the top view vs imac_data.core.cameras.project of the cube
    (frame 0 is the reset state: gym-aloha's sampled pose for the episode seed)."""
    out, paths, cfg = cube_dir
    from scipy.spatial import ConvexHull

    ep = read_episode(paths[0], load_segmentation=True)
    calib = load_calibration(out / "calibration.json")["cam_high"]
    box = next(g for g, (name, _) in ep.segmentation_labels.items() if name == "red_box")
    v, u = np.nonzero(ep.segmentation["cam_high"][0] == box)
    assert len(u) > 20
    seg_centroid = np.array([u.mean(), v.mean()])

    pose = sample_box_pose(cfg.seed)
    assert np.allclose(pose[3:], [1, 0, 0, 0])
    corners = pose[:3] + 0.02 * np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    pts = torch.tensor(np.vstack([pose[:3], corners]), dtype=torch.float64)
    uv, z = project(pts, torch.tensor(calib.K), torch.tensor(calib.T_world_cam))
    uv = uv.numpy()
    assert (z > 0).all()
    assert np.linalg.norm(uv[0] - seg_centroid) < 1.0
    # Sharper: the silhouette of a box is the convex hull of its projected corners, and
    # the rasteriser keeps the pixels whose centres fall inside it.
    hull = uv[1:][ConvexHull(uv[1:]).vertices]  # counter-clockwise
    grid_v, grid_u = np.mgrid[0:calib.height, 0:calib.width]
    inside = np.ones(grid_u.shape, dtype=bool)
    for (x0, y0), (x1, y1) in zip(hull, np.roll(hull, -1, axis=0)):
        inside &= (x1 - x0) * (grid_v - y0) - (y1 - y0) * (grid_u - x0) >= 0
    rendered = ep.segmentation["cam_high"][0] == box
    assert (inside ^ rendered).sum() <= 2, "rendered cube and projected cube disagree"
    # And the robot pixels are where the robot is: the gripper origins project onto robot pixels.
    mask = robot_mask(ep.segmentation["cam_high"][0], ep.segmentation_labels)
    for arm_xyz in ([-0.31718881, 0.5, 0.29525084], [0.31718881, 0.5, 0.29525084]):  # gripper_link at start
        p, _ = project(torch.tensor([arm_xyz], dtype=torch.float64), torch.tensor(calib.K),
                       torch.tensor(calib.T_world_cam))
        uc, vc = np.rint(p[0].numpy()).astype(int)
        assert mask[vc - 1: vc + 2, uc - 1: uc + 2].any()


def test_robot_mask_is_the_arm_subtrees():
    model = load_mujoco_model("insertion")
    labels = segmentation_labels(model)
    roots = {model.body(n).id for n in ("vx300s_left", "vx300s_right")}
    truth = np.array([model.body_rootid[model.geom_bodyid[g]] in roots for g in range(model.ngeom)])
    seg = np.r_[-1, np.arange(model.ngeom)].astype(np.int16).reshape(1, -1)
    mask = robot_mask(seg, labels)
    assert mask.shape == seg.shape and mask.dtype == bool
    assert not mask[0, 0]
    np.testing.assert_array_equal(mask[0, 1:], truth)
    assert 0 < truth.sum() < model.ngeom


# --------------------------------------------------------------------------- policy


@pytest.mark.parametrize("task", ["transfer_cube", "insertion"])
def test_noiseless_policy_succeeds_and_noisy_one_fails(task):
    for seed in range(3):
        r = simulate_episode(task, seed, noise=0.0)
        assert r.success, f"{task} seed {seed} failed at noise 0 (max reward {r.max_reward})"
        assert r.max_reward >= (4 if task == "transfer_cube" else 3)
    noisy = [simulate_episode(task, seed, noise=1.0).success for seed in range(4)]
    assert not all(noisy), f"{task}: every noisy episode succeeded"


def test_rollouts_are_reproducible_and_held_per_frame():
    a = simulate_episode("insertion", 7, noise=0.5, max_steps=60)
    b = simulate_episode("insertion", 7, noise=0.5, max_steps=60)
    np.testing.assert_array_equal(a.action, b.action)
    np.testing.assert_array_equal(a.qpos, b.qpos)
    assert a.num_frames == 30 and a.fps == 25.0
    c = simulate_episode("insertion", 8, noise=0.5, max_steps=60)
    assert not np.array_equal(a.action, c.action)
    # Frame k's state is before action k; the arm moves toward the held targets.
    s1 = simulate_episode("transfer_cube", 0, frame_stride=1, max_steps=40)
    assert s1.num_frames == 40 and s1.fps == 50.0
    err_before = np.abs(s1.action[10:-1, :6] - s1.qpos[10:-1, :6]).sum()
    err_after = np.abs(s1.action[10:-1, :6] - s1.qpos[11:, :6]).sum()
    assert err_after < err_before


# --------------------------------------------------------------------------- inputs and CLI


@pytest.mark.parametrize(
    "field, value",
    [
        ("task", "stack_blocks"),
        ("num_episodes", 0),
        ("num_episodes", 1.5),
        ("width", 0),
        ("height", -240),
        ("seed", -1),
        ("noise", 1.5),
        ("noise", math.nan),
        ("noise", "high"),
        ("frame_stride", 0),
        ("max_steps", 1),
        ("jpeg_quality", 101),
        ("with_segmentation", "yes"),
    ],
)
def test_invalid_config_names_the_field(field, value):
    with pytest.raises(InputError, match=rf"SimConfig\.{field}"):
        SimConfig(**{field: value})


def test_refuses_to_mix_datasets_and_cli_summary(tmp_path, capsys):
    out = tmp_path / "cli"
    argv = ["--task", "transfer_cube", "--episodes", "1", "--out", str(out), "--height", "48", "--width", "64",
            "--max-steps", "4", "--quiet", "--no-depth"]
    assert imac_main(["simulate", *argv]) == 0
    line = capsys.readouterr().out.strip()
    assert line.startswith("transfer_cube: 1 episodes, 0 successes, 2 frames") and " s -> " in line
    assert probe_episode(out / "episode_0.hdf5")["has_depth"] is False
    assert imac_main(["simulate", *argv]) == 2  # out already holds episodes
    assert "already holds" in capsys.readouterr().err
    assert imac_main(["simulate", *argv, "--overwrite"]) == 0
    assert imac_main(["simulate", *argv[:-2], "--noise", "2"]) == 2
    assert "SimConfig.noise" in capsys.readouterr().err
