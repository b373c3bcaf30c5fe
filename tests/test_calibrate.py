"""Calibration from the robot itself (``qa refine``, :mod:`imac_data.calibrate`).

The oracle is the simulator: its rig's calibration is exact (our render matches MuJoCo's
robot pixels to IoU 0.9999), so a perturbed copy has a known truth to return to. Small
resolution (160x120) to stay inside the CI budget; the 640x480 figures are in
``benchmarks/calibration_refine.py``.

Tolerances at 160x120, from the pixel size: the head camera (fovy 78 deg) has fy = 74 px,
i.e. 0.77 deg and about 11 mm (at the robot, 0.8 m away) per pixel; the wrist cameras
(fy = 340 px) 0.17 deg per pixel. We ask for a quarter pixel at the head (0.2 deg, 3 mm)
and about a pixel at the wrist (0.2 deg, 2 mm), from a start 20-50 mm and 2-5 deg off
(head) and 10 mm and 3 deg off (wrist), i.e. 5-30 px.
"""

import hashlib
import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from imac_data.calibrate.config import RefineConfig
from imac_data.calibrate.frames import select_frames
from imac_data.calibrate.objective import SoftSilhouette, exact_energy, make_level, render_level
from imac_data.calibrate.pose import apply_update, pose_change
from imac_data.cli import main as imac_main
from imac_data.core.cameras import load_calibration, save_calibration
from imac_data.core.render import RaycastRenderer
from imac_data.core.robot import aloha
from imac_data.core.robot.model import RobotModel
from imac_data.errors import InputError
from imac_data.sources.hdf5 import RawEpisode, read_episode, write_episode
from imac_data.sources.sim import rig as sim_rig
from imac_data.sources.sim.recorder import SimConfig, record_dataset

REPO = Path(__file__).resolve().parent.parent
RECIPE = REPO / "recipes" / "aloha_sim_transfer_cube.yaml"


def sim_near() -> str:
    """MuJoCo's near clip plane (``znear * extent``): the simulator's masks are clipped there."""
    model = sim_rig.load_mujoco_model("transfer_cube")
    return str(model.vis.map.znear * model.stat.extent)


@pytest.fixture(scope="module")
def sim_src(tmp_path_factory):
    """One whole scripted episode (125 frames) at 160x120 with MuJoCo's segmentation."""
    out = tmp_path_factory.mktemp("calib_sim")
    record_dataset(SimConfig(num_episodes=1, width=160, height=120, with_segmentation=True, noise=0.0), out,
                   progress=False)
    return out


@pytest.fixture(scope="module")
def robot():
    return RobotModel(aloha.robot_config())


def perturbed(calib: dict, seed: int) -> dict:
    """The issue's perturbation: head 2-5 cm and 2-5 deg, wrist mounts 1 cm and 3 deg."""
    rng = np.random.default_rng(seed)
    out = {}
    for name, cam in calib.items():
        t, r = (1.0, 3.0) if cam.is_mounted else (rng.uniform(2, 5), rng.uniform(2, 5))
        dt, dr = rng.normal(size=3), rng.normal(size=3)
        out[name] = apply_update(cam, np.r_[dt / np.linalg.norm(dt) * t, dr / np.linalg.norm(dr) * r])
    return out


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


# ----------------------------------------------------------------------------- pieces (analytic)


def test_pose_update_and_change_are_in_camera_axes():
    """Moving a camera by 1 cm along its own x and 3 deg about its own y reads back as exactly
    that, for a fixed and a mounted camera, whatever the camera's orientation in its parent."""
    from scipy.spatial.transform import Rotation

    calib = sim_rig.camera_calibration(sim_rig.load_mujoco_model("transfer_cube"), 160, 120)
    for cam in (calib["cam_high"], calib["cam_left_wrist"]):
        moved = apply_update(cam, [1.0, 0, 0, 0, 3.0, 0])
        change = pose_change(cam, moved)
        # the rotation built by hand: R' = R @ R_y(3 deg), in the camera's own axes
        R_y = Rotation.from_rotvec([0, math.radians(3.0), 0]).as_matrix()
        parent = cam.T_link_cam if cam.is_mounted else cam.T_world_cam
        got = moved.T_link_cam if cam.is_mounted else moved.T_world_cam
        assert np.allclose(got[:3, :3], parent[:3, :3] @ R_y, atol=1e-12)
        assert change["ry_deg"] == pytest.approx(3.0, abs=1e-9)
        assert abs(change["rx_deg"]) < 1e-9 and abs(change["rz_deg"]) < 1e-9
        # exp of a twist: the translation is V v, whose x part stays ~1 cm for a small rotation
        assert change["x_mm"] == pytest.approx(10.0, abs=0.01)
        assert change["t_mm"] == pytest.approx(10.0, abs=0.01)
        centre_shift = (got[:3, 3] - parent[:3, 3]) * 1000.0
        assert np.allclose(parent[:3, :3].T @ centre_shift, [change["x_mm"], change["y_mm"], change["z_mm"]])


def test_select_frames_spreads_configurations_and_refuses_degenerate_sets():
    rng = np.random.default_rng(0)
    q = np.concatenate([np.zeros((20, 14)), rng.normal(size=(40, 14))])  # 20 copies of one pose
    coverage = np.full(len(q), 0.2)
    idx = select_frames(q, coverage, 8)
    assert len(idx) == 8 and len(set(idx.tolist())) == 8
    assert sum(i < 20 for i in idx) <= 1  # the repeated pose counts once
    d = np.linalg.norm(q[idx][:, None] - q[idx][None], axis=-1) + np.eye(8) * 1e9
    assert d.min() >= 0.1
    with pytest.raises(InputError, match="no robot visible.*cam_x"):
        select_frames(q, np.zeros(len(q)), 8, camera="cam_x")
    with pytest.raises(InputError, match="too few distinct poses.*only 1 joint"):
        select_frames(np.zeros((30, 14)), np.full(30, 0.3), 8)


def test_soft_objective_equals_the_exact_one_at_zero(sim_src, robot):
    """The differentiable objective, built around an exact render, reproduces that render's
    objective at zero update (IoU and edge term), so the exact render can judge its steps."""
    ep = read_episode(sim_src / "episode_0.hdf5", cameras=["cam_high"], load_depth=False, load_segmentation=True)
    from imac_data.qa.overlay import ground_truth_robot_mask

    renderer = RaycastRenderer(robot)
    idx = [20, 60, 100]
    target = ground_truth_robot_mask(ep.segmentation["cam_high"][idx], ep.segmentation_labels, renderer.link_names)
    cam = perturbed(load_calibration(sim_src / "calibration.json"), 0)["cam_high"]
    q = torch.as_tensor(ep.qpos[idx])
    for cfg in (RefineConfig(iou_weight=1.0, edge_weight=0.1), RefineConfig(robust="huber", edge_scale_px=2.0)):
        lv = make_level(cam, target.astype(np.float32), 1.0, cfg.pad, False)
        v = render_level(renderer, cam, q, lv, cfg)
        soft = SoftSilhouette(v, cam, lv, cfg, cfg.step_px)
        assert float(soft.energy(torch.zeros(7, dtype=torch.float64))) == pytest.approx(v.energy, rel=1e-4)
        assert v.energy == pytest.approx(exact_energy(v, lv, cfg)[0])
        assert 0 < v.iou < 1


# ----------------------------------------------------------------------------- the command


def test_refine_returns_to_the_truth_with_sim_masks(sim_src, tmp_path, capsys):
    """`qa refine` from a calibration 2-5 cm / 2-5 deg (head) and 1 cm / 3 deg (wrist) off comes back
    to the simulator's exact calibration; the output loads, the input is untouched, the camera
    not asked for is copied through, and the report has the before/after figures and overlays."""
    truth = load_calibration(sim_src / "calibration.json")
    start = perturbed(truth, 1)
    bad = tmp_path / "bad.json"
    save_calibration(bad, start)
    before = digest(bad)
    out = tmp_path / "refined.json"
    rc = imac_main(["qa", "refine", str(sim_src), "--recipe", str(RECIPE), "--calibration", str(bad), "--out", str(out),
                  "--cameras", "cam_high,cam_right_wrist", "--robot-pixels", "sim", "--near", sim_near()])
    printed = capsys.readouterr().out
    assert rc == 0, printed
    assert digest(bad) == before
    refined = load_calibration(out)  # the README's format, loadable
    assert set(refined) == set(truth)
    assert np.array_equal(refined["cam_left_wrist"].T_link_cam, start["cam_left_wrist"].T_link_cam)
    tol = {"cam_high": (3.0, 0.2), "cam_right_wrist": (2.0, 0.2)}
    for c, (mm, deg) in tol.items():
        assert pose_change(truth[c], start[c])["t_mm"] >= 9.9  # it did start far off
        err = pose_change(truth[c], refined[c])
        assert err["t_mm"] <= mm and err["r_deg"] <= deg, (c, err)
        assert refined[c].link == truth[c].link and np.array_equal(refined[c].K, start[c].K)
    report = json.loads((tmp_path / "refined.report" / "report.json").read_text())
    for c in tol:
        e = report["cameras"][c]
        assert e["iou_after"] > 0.97 and e["iou_after"] > e["iou_before"] + 0.05
        assert e["boundary_px_after"] < e["boundary_px_before"]
        assert set(e["pose_change"]) >= {"x_mm", "y_mm", "z_mm", "rx_deg", "ry_deg", "rz_deg"}
        assert len(e["frames"]) == 8
        for when in ("before", "after"):
            img = cv2.imread(str(tmp_path / "refined.report" / f"{c}_{when}.png"))
            assert img is not None and img.shape[0] > 100
    assert "cam_high" in printed and "IoU" in printed

    # never over the input, and an existing output needs --overwrite
    assert imac_main(["qa", "refine", str(sim_src), "--recipe", str(RECIPE), "--calibration", str(bad), "--out",
                    str(bad)]) == 2
    assert "never overwritten" in capsys.readouterr().err
    assert imac_main(["qa", "refine", str(sim_src), "--recipe", str(RECIPE), "--calibration", str(bad), "--out",
                    str(out)]) == 2
    assert "--overwrite" in capsys.readouterr().err
    assert digest(bad) == before


def test_refine_a_lerobot_dataset_with_a_segmenters_masks(sim_src, tmp_path, capsys):
    """A dataset built with a wrong head calibration: `qa refine DATASET` takes the rig from the
    dataset itself (no recipe), the robot's pixels from a mask directory (a 'segmenter' whose
    masks are the simulator's), the frames through LeRobot's decoder, and returns the head
    camera to the simulator's exact calibration. The dataset is not modified."""
    from imac_data.build.from_episodes import ingest_episodes
    from imac_data.core.rig import Rig
    from imac_data.dataset.ingest import IngestOptions
    from imac_data.qa.overlay import ground_truth_robot_mask
    from imac_data.recipes import load_recipe

    truth = load_calibration(sim_src / "calibration.json")
    start = perturbed(truth, 2)
    bad = tmp_path / "bad.json"
    save_calibration(bad, start)
    rig = Rig.from_recipe(load_recipe(RECIPE), bad)
    root = tmp_path / "ds"
    ingest_episodes([sim_src / "episode_0.hdf5"], rig=rig, repo_id="local/ds", root=root,
                    options=IngestOptions(fps=25, task="t", state_names=aloha.STATE_NAMES, vcodec="libx264"),
                    progress=False)
    ep = read_episode(sim_src / "episode_0.hdf5", cameras=["cam_high"], load_depth=False, load_segmentation=True)
    folder = tmp_path / "masks" / "episode_000000" / "cam_high"
    folder.mkdir(parents=True)
    for t in range(0, ep.num_frames, 4):
        m = ground_truth_robot_mask(ep.segmentation["cam_high"][t], ep.segmentation_labels, rig.robot.link_names)
        cv2.imwrite(str(folder / f"{t:06d}.png"), m.astype(np.uint8) * 255)
    # the dataset reader against the raw episode: the same joint vectors, the same frames (lossy video)
    from imac_data.calibrate.frames import DatasetFrames

    frames = DatasetFrames(root)
    assert frames.cameras == ["cam_high", "cam_left_wrist", "cam_right_wrist"]
    assert np.allclose(frames.joints("0"), ep.qpos, atol=1e-6)
    got = frames.images("0", "cam_high", [10, 90]).astype(np.float32)
    raw = ep.images["cam_high"][[10, 90]].astype(np.float32)
    same, swapped = np.abs(got - raw).mean(axis=(1, 2, 3)), np.abs(got - raw[::-1]).mean(axis=(1, 2, 3))
    assert (same < 3.0).all() and (same < swapped).all(), (same, swapped)
    info = digest(root / "meta" / "info.json")
    out = tmp_path / "refined.json"
    rc = imac_main(["qa", "refine", str(root), "--out", str(out), "--cameras", "cam_high", "--robot-pixels",
                  str(tmp_path / "masks"), "--near", sim_near()])
    assert rc == 0, capsys.readouterr().err
    assert digest(root / "meta" / "info.json") == info
    refined = load_calibration(out)
    assert pose_change(truth["cam_high"], start["cam_high"])["t_mm"] >= 20  # it did start far off
    err = pose_change(truth["cam_high"], refined["cam_high"])
    assert err["t_mm"] <= 3.0 and err["r_deg"] <= 0.2, err
    frames = json.loads((tmp_path / "refined.report" / "report.json").read_text())["cameras"]["cam_high"]["frames"]
    assert len(frames) == 8 and all(t % 4 == 0 for _, t in frames)  # only frames that have a mask
    # raw episodes need a recipe: only a dataset carries its rig
    assert imac_main(["qa", "refine", str(sim_src), "--out", str(tmp_path / "r2.json")]) == 2
    assert "--recipe is required" in capsys.readouterr().err


def test_refine_refuses_views_without_the_robot(sim_src, tmp_path, capsys):
    """Masks that never show the robot (here: empty masks from a 'segmenter') get a clear message,
    and nothing is written."""
    masks = tmp_path / "masks" / "episode_0" / "cam_high"
    masks.mkdir(parents=True)
    for t in range(0, 125, 5):
        cv2.imwrite(str(masks / f"{t:06d}.png"), np.zeros((120, 160), np.uint8))
    out = tmp_path / "refined.json"
    rc = imac_main(["qa", "refine", str(sim_src), "--recipe", str(RECIPE), "--calibration", str(sim_src / "calibration.json"),
                  "--out", str(out), "--cameras", "cam_high", "--robot-pixels", str(tmp_path / "masks")])
    err = capsys.readouterr().err
    assert rc == 2
    assert "no robot visible in camera 'cam_high'" in err
    assert not out.exists() and not (tmp_path / "refined.report").exists()


def test_refine_refuses_too_few_distinct_poses(sim_src, tmp_path, capsys):
    """An episode in which the robot holds still pins nothing down along the view: refused."""
    ep = read_episode(sim_src / "episode_0.hdf5", load_segmentation=True)
    still = tmp_path / "still"
    still.mkdir()
    keep = [40] * 30
    write_episode(still / "episode_0.hdf5", RawEpisode(
        qpos=ep.qpos[keep], action=ep.action[keep], images={c: v[keep] for c, v in ep.images.items()},
        segmentation={c: v[keep] for c, v in ep.segmentation.items()}, segmentation_labels=ep.segmentation_labels,
        fps=ep.fps))
    out = tmp_path / "refined.json"
    rc = imac_main(["qa", "refine", str(still), "--recipe", str(RECIPE), "--calibration", str(sim_src / "calibration.json"),
                  "--out", str(out), "--cameras", "cam_high"])
    err = capsys.readouterr().err
    assert rc == 2
    assert "too few distinct poses in camera 'cam_high'" in err and "only 1 joint configuration" in err
    assert not out.exists()


def test_edge_cue_needs_an_overlay_that_shows_the_robot(sim_src, tmp_path, capsys):
    """The built-in cue looks for the robot's outline near the current overlay; a calibration that
    renders no robot at all (the head camera turned to look up) is refused clearly."""
    calib = load_calibration(sim_src / "calibration.json")
    away = tmp_path / "away.json"
    save_calibration(away, {**calib, "cam_high": apply_update(calib["cam_high"], [0, 0, 0, 180.0, 0, 0])})
    rc = imac_main(["qa", "refine", str(sim_src), "--recipe", str(RECIPE), "--calibration", str(away),
                  "--out", str(tmp_path / "r.json"), "--cameras", "cam_high", "--robot-pixels", "edges"])
    assert rc == 2
    assert "no robot visible in camera 'cam_high'" in capsys.readouterr().err


def test_refine_config_is_validated_and_round_trips():
    cfg = RefineConfig(method="nelder-mead", levels=[0.5, 1.0], refine_focal=True)
    assert RefineConfig(**json.loads(json.dumps(cfg.to_dict()))) == cfg
    for bad, field in (({"method": "adam"}, "method"), ({"levels": (1.0, 0.5)}, "levels"),
                       ({"robust": "l1"}, "robust"), ({"iou_weight": 0.0, "edge_weight": 0.0}, "edge_weight"),
                       ({"max_iterations": 0}, "max_iterations"), ({"pad": 2.0}, "pad")):
        with pytest.raises(InputError, match=f"RefineConfig.{field}"):
            RefineConfig(**bad)
