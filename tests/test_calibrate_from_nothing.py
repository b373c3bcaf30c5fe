"""Calibration from nothing (``qa calibrate``, :mod:`imac_data.calibrate.from_nothing`).

The oracle is the simulators' own cameras, never shown to the command: its inputs are plain
HDF5 episodes (joint states, RGB, depth in mm) with no calibration and no segmentation, the
image size and a nominal field of view 15 % off. Small versions of the benchmark's cases
(``benchmarks/calibration_from_nothing.py``, 480x640) at 120x160, one placement each, plus
every refusal. Goals as the benchmark's: head 3 mm / 0.3 deg, wrist 5 mm / 0.5 deg.
"""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from benchmarks.calibration_scenes import (
    ALOHA_FOVY,
    ALOHA_MOUNTS,
    ALOHA_NEAR,
    ALOHA_RECIPE,
    aloha_episodes,
    aloha_placements,
    degrade_depth,
    random_placements,
)
from imac_data.calibrate.from_nothing import _plausible, calibrate_from_nothing
from imac_data.calibrate.register import Fit
from imac_data.calibrate.scratch import CalibrationRefused, CameraResult, ScratchConfig, _judge, pose_distance
from imac_data.cli import main as imac_main
from imac_data.core.cameras import load_calibration, look_at
from imac_data.core.render import RaycastRenderer
from imac_data.core.robot import aloha
from imac_data.core.robot.model import RobotModel
from imac_data.errors import InputError
from imac_data.sources.hdf5 import RawEpisode, read_episode, write_episode

HW = (120, 160)


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    """One scripted transfer-cube episode (150 frames) at 120x160: the episodes and the hidden truth."""
    out = tmp_path_factory.mktemp("scratch") / "episodes"
    truth = aloha_episodes(out, seed=3, episodes=1, height=HW[0], width=HW[1], max_steps=300)
    return out, truth


def error(truth, found) -> tuple[float, float]:
    a = truth.T_link_cam if truth.is_mounted else truth.T_world_cam
    b = found.T_link_cam if found.is_mounted else found.T_world_cam
    return pose_distance(a, b)


def digests(folder: Path) -> dict:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.iterdir())}


def test_aloha_head_and_wrist_from_nothing_then_refined(sim, tmp_path, capsys):
    """The command end to end: no calibration anywhere in the source, nominal FOV 15 % too wide;
    the head camera and a wrist mount come back within the goals, the focal length within 1 %,
    the result goes through `qa refine` (edge cue) and the report has the confidence figures and
    the overlays before and after. The source is not touched."""
    src, truth = sim
    assert not list(src.glob("*.json"))
    before = digests(src)
    out = tmp_path / "calib.json"
    args = ["qa", "calibrate", str(src), "--recipe", str(ALOHA_RECIPE), "--out", str(out),
            "--cameras", "cam_high,cam_left_wrist", "--mount", f"cam_left_wrist={ALOHA_MOUNTS['cam_left_wrist']}",
            "--fov", f"cam_high={ALOHA_FOVY['cam_high'] * 1.15}", "--fov", f"{ALOHA_FOVY['cam_left_wrist'] * 1.15}",
            "--near", str(ALOHA_NEAR), "--no-progress"]
    assert imac_main(args) == 0, capsys.readouterr().err
    printed = capsys.readouterr().out
    assert "cam_high" in printed and "inliers" in printed
    found = load_calibration(out)
    assert set(found) == {"cam_high", "cam_left_wrist"} and found["cam_left_wrist"].link == ALOHA_MOUNTS["cam_left_wrist"]
    for c, (mm, deg) in {"cam_high": (3.0, 0.3), "cam_left_wrist": (5.0, 0.5)}.items():
        t, r = error(truth[c], found[c])
        assert t <= mm and r <= deg, (c, t, r)
        assert found[c].K[0, 0] == pytest.approx(truth[c].K[0, 0], rel=0.01)
        assert found[c].K[0, 2] == truth[c].K[0, 2]  # principal point: the image centre
    report = json.loads((tmp_path / "calib.report" / "report.json").read_text())
    for c in found:
        e = report["cameras"][c]
        assert e["inlier_ratio"] > 0.9 and e["residual_mm"] < 2.0
        assert e["outline_px_after_refine"] is not None and isinstance(e["refine_accepted"], bool)
        for when in ("before", "after"):
            assert (tmp_path / "calib.report" / f"{c}_{when}_refine.png").stat().st_size > 1000
    assert report["refused"] == {}
    assert digests(src) == before
    # an existing output needs --overwrite; nothing else is written
    assert imac_main(args) == 2
    assert "--overwrite" in capsys.readouterr().err


def test_head_camera_at_a_random_placement(sim, tmp_path):
    """A fixed camera 1-2 m away at a random pose over the hemisphere in front of the rig, MuJoCo's
    depth, nominal FOV 15 % off: within 3 mm and 0.3 deg."""
    poses = random_placements(1, 2026, centre=(0.0, 0.5, 0.15), front=(0, -1, 0), base=(0.0, 0.5, 0.0))
    truth = aloha_placements(tmp_path / "eps", sim[0], poses, fovy=45.0, height=HW[0], width=HW[1])
    out = tmp_path / "calib.json"
    calibrate_from_nothing(tmp_path / "eps", out, recipe=ALOHA_RECIPE, fov={"*": 45.0 * 1.15}, refine="none",
                           progress=False)
    t, r = error(truth["cam_rand_00"], load_calibration(out)["cam_rand_00"])
    assert t <= 3.0 and r <= 0.3, (t, r)


@pytest.mark.skipif(sys.version_info >= (3, 12), reason="pybullet has no wheel for Python 3.12+")
def test_a_second_robot_through_a_recipe_only(tmp_path):
    """The Franka Panda URDF that pybullet ships, rendered by pybullet, through the same command:
    the recipe is the only Panda-specific input."""
    from benchmarks.calibration_scenes import panda_episodes, panda_recipe

    poses = random_placements(1, 7, centre=(0.35, 0.0, 0.35), front=(1, 0, 0))
    truth = panda_episodes(tmp_path, poses, seed=3, height=HW[0], width=HW[1], episodes=1, frames=30)
    out = tmp_path / "calib.json"
    calibrate_from_nothing(tmp_path / "episodes", out, recipe=panda_recipe(tmp_path), fov={"*": 60.0 * 0.85},
                           refine="none", candidates=30, progress=False)
    t, r = error(truth["cam_rand_00"], load_calibration(out)["cam_rand_00"])
    assert t <= 3.0 and r <= 0.3, (t, r)


def test_scaled_noisy_depth_and_a_wrong_focal_length(sim, tmp_path):
    """Depth x1.07 with Gaussian noise of 1 % of the range and a focal 15 % off: the head camera
    within 5 mm and 0.5 deg, and the depth scale reported within 1 % (it undoes the 1.07)."""
    src, truth = sim
    degrade_depth(src, tmp_path / "eps", "cam_high", scale=1.07, noise=0.01, seed=0)
    out = tmp_path / "calib.json"
    summary = calibrate_from_nothing(tmp_path / "eps", out, recipe=ALOHA_RECIPE, cameras=["cam_high"],
                                     fov={"cam_high": 78.0 * 1.15}, estimate_depth_scale=True, refine="none",
                                     progress=False)
    t, r = error(truth["cam_high"], load_calibration(out)["cam_high"])
    assert t <= 5.0 and r <= 0.5, (t, r)
    assert summary["cameras"]["cam_high"]["depth_scale"] * 1.07 == pytest.approx(1.0, abs=0.01)


# ----------------------------------------------------------------------------- refusals


def _copy(src: Path, out: Path, edit) -> Path:
    out.mkdir()
    for p in sorted(src.glob("*.hdf5")):
        write_episode(out / p.name, edit(read_episode(p)), sim=False)
    return out


def test_refuses_without_depth_and_says_what_to_do(sim, tmp_path, capsys):
    src = _copy(sim[0], tmp_path / "eps", lambda ep: RawEpisode(ep.qpos, ep.action, ep.images))
    out = tmp_path / "calib.json"
    rc = imac_main(["qa", "calibrate", str(src), "--recipe", str(ALOHA_RECIPE), "--out", str(out),
                    "--cameras", "cam_high", "--fov", "78", "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2
    assert "cam_high" in err and "no depth" in err and "--depth da3" in err and "qa refine" in err
    assert "outside the URDF limits" not in err  # joints in the joint map's units: no limit warning
    assert not out.exists() and not (tmp_path / "calib.report").exists()


def test_joints_outside_the_urdf_limits_are_warned_before_the_search(sim, tmp_path, capsys):
    """The build's joint-limit check runs first: a state in degrees under the recipe's radian joint map
    gets its warning (the joints, the scale that fixes it, and that a poor fit may be this, not the
    cameras) before anything else; this run then stops at its cheap refusal (no depth)."""
    src = _copy(sim[0], tmp_path / "eps", lambda ep: RawEpisode(np.degrees(ep.qpos), ep.action, ep.images))
    rc = imac_main(["qa", "calibrate", str(src), "--recipe", str(ALOHA_RECIPE), "--out", str(tmp_path / "calib.json"),
                    "--cameras", "cam_high", "--fov", "78", "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2 and "no depth" in err
    assert f"warning: {src}: recorded joint values lie outside the URDF limits of robot 'aloha'" in err
    assert "if it records degrees, give it scale: 0.01745329" in err and "Calibration goes on" in err
    assert err.index("outside the URDF limits") < err.index("no depth")


def test_refuses_a_single_arm_pose_repeated_in_every_frame(sim, tmp_path):
    def frozen(ep):
        n = 40
        return RawEpisode(np.repeat(ep.qpos[60:61], n, 0), np.repeat(ep.action[60:61], n, 0),
                          {c: np.repeat(v[60:61], n, 0) for c, v in ep.images.items()},
                          depth_mm={c: np.repeat(v[60:61], n, 0) for c, v in ep.depth_mm.items()})

    src = _copy(sim[0], tmp_path / "eps", frozen)
    with pytest.raises(CalibrationRefused, match=r"camera 'cam_high': too few distinct arm poses"):
        calibrate_from_nothing(src, tmp_path / "calib.json", recipe=ALOHA_RECIPE, cameras=["cam_high"],
                               fov={"*": 78.0}, refine="none", progress=False)
    assert not (tmp_path / "calib.json").exists()


def test_refuses_a_camera_that_sees_too_little_of_the_robot(sim, tmp_path):
    """A camera 6 m away: the robot covers under 1 % of its view (checked with our renderer and
    the hidden truth); the camera is refused by name, a good camera in the same run is written."""
    far = look_at([0.0, -5.5, 2.5], [0.0, 0.5, 0.15])
    near = random_placements(1, 2026, centre=(0.0, 0.5, 0.15), front=(0, -1, 0), base=(0.0, 0.5, 0.0))[0]
    truth = aloha_placements(tmp_path / "eps", sim[0], [near, far], fovy=45.0, height=HW[0], width=HW[1])
    robot = RobotModel(aloha.robot_config())
    q = torch.as_tensor(read_episode(sim[0] / "episode_0.hdf5", load_depth=False).qpos[::10])
    cover = RaycastRenderer(robot).render(q, {"c": truth["cam_rand_01"]})["c"].mask.float().mean(dim=(1, 2))
    assert float(cover.max()) < 0.01
    summary = calibrate_from_nothing(tmp_path / "eps", tmp_path / "calib.json", recipe=ALOHA_RECIPE,
                                     fov={"*": 45.0}, refine="none", progress=False)
    assert "robot too small in view" in summary["refused"]["cam_rand_01"]
    assert "camera 'cam_rand_01'" in summary["refused"]["cam_rand_01"]
    assert set(load_calibration(tmp_path / "calib.json")) == {"cam_rand_00"}


def test_bad_input_is_refused_before_any_work(sim, tmp_path):
    src = sim[0]
    kw = dict(recipe=ALOHA_RECIPE, refine="none", progress=False)
    out = tmp_path / "calib.json"
    with pytest.raises(InputError, match="cam_left_wrist.*--mount"):
        calibrate_from_nothing(src, out, fov={"*": 60.0}, **kw)
    with pytest.raises(InputError, match="no link 'nope'"):
        calibrate_from_nothing(src, out, fov={"*": 60.0}, mounts={"cam_left_wrist": "nope"}, cameras=["cam_left_wrist"],
                               **kw)
    with pytest.raises(InputError, match="--fov for camera 'cam_high'"):
        calibrate_from_nothing(src, out, cameras=["cam_high"], fov={"cam_high": 500.0}, **kw)
    with pytest.raises(InputError, match="not in the source"):
        calibrate_from_nothing(src, out, cameras=["cam_x"], fov={"*": 60.0}, **kw)
    with pytest.raises(InputError, match="is the source|inside"):
        calibrate_from_nothing(src, src / "calib.json", cameras=["cam_high"], fov={"*": 60.0}, **kw)
    with pytest.raises(InputError, match="ScratchConfig.frames"):
        ScratchConfig(frames=2)
    assert not out.exists() and not list(tmp_path.iterdir())


def test_depth_anything_3_pose_free_mode_and_missing_weights(sim, tmp_path):
    """DA3's pose-free mode needs images and a focal guess only; its scale follows the guess
    (random weights: the plumbing, not the depth). Without weights the command stops before any work."""
    pytest.importorskip("depth_anything_3")
    from imac_data.sources.da3 import DepthAnything3Metric

    net = DepthAnything3Metric.random_init("da3-small", process_res=56, batch_size=2, device="cpu")
    images = read_episode(sim[0] / "episode_0.hdf5", load_depth=False).images["cam_high"][:2]
    d1 = net.predict_pose_free(images, 100.0)
    d2 = net.predict_pose_free(images, 50.0)
    assert d1.shape == (2, *HW) and np.isfinite(d1).all()
    np.testing.assert_allclose(d2, d1 / 2, rtol=1e-5, atol=1e-7)
    with pytest.raises(InputError, match="Depth Anything 3 weights"):
        calibrate_from_nothing(sim[0], tmp_path / "calib.json", recipe=ALOHA_RECIPE, cameras=["cam_high"],
                               fov={"*": 78.0}, depth="da3", da3_model=str(tmp_path / "no_weights"), progress=False)
    assert not list(tmp_path.iterdir())


def test_two_different_poses_that_fit_alike_are_refused_as_ambiguous():
    """The judge of the candidates: a runner-up 5 cm away scoring 95 % of the best is refused by
    name; one scoring half is not; a best that explains too little is refused too."""
    from imac_data.calibrate.register import Fit
    from imac_data.calibrate.scratch import _judge

    cfg = ScratchConfig()
    a, b = np.eye(4), np.eye(4)
    b[:3, 3] = [0.05, 0.0, 0.0]
    with pytest.raises(CalibrationRefused, match=r"camera 'cam_x': ambiguous: two poses 50 mm"):
        _judge("cam_x", [Fit(a, 500.0, 1.0, 0.95, 0.8, 10), Fit(b, 500.0, 1.0, 0.91, 0.8, 10)], cfg)
    best, conf = _judge("cam_x", [Fit(a, 500.0, 1.0, 0.95, 0.8, 10), Fit(b, 500.0, 1.0, 0.5, 3.0, 10)], cfg)
    assert best.X is a and conf["runner_up_inlier_ratio"] == 0.5
    with pytest.raises(CalibrationRefused, match=r"camera 'cam_x': no pose explains the depth"):
        _judge("cam_x", [Fit(a, 500.0, 1.0, 0.6, 0.8, 10)], cfg)


def test_an_ambiguous_refusal_names_the_joint_map_before_the_frames():
    """Two different poses fitting about alike most often mean a robot posed wrongly: the SO-101 block copied in
    the URDF's joint order gave two poses 156 mm and 73.5 deg apart. The refusal names the joint map, its order and
    its units, before the advice on frames and on `qa refine`."""
    a, b = np.eye(4), np.eye(4)
    b[:3, 3] = [0.156, 0.0, 0.0]
    with pytest.raises(CalibrationRefused) as refused:
        _judge("front", [Fit(a, 500.0, 1.0, 0.92, 0.8, 10), Fit(b, 500.0, 1.0, 0.9, 0.8, 10)], ScratchConfig())
    msg = str(refused.value)
    assert msg.startswith("camera 'front': ambiguous: two poses 156 mm and 0.0 deg apart")
    advice = msg[msg.index("inliers)"):]
    first = advice.index("check the joint map")
    assert first < advice.index("order") < advice.index("unit") < advice.index("frames where more of the arm moves")
    assert advice.index("frames where") < advice.index("`imac qa refine`")
    assert "imac robot joints" in advice[:advice.index("frames where")]


def test_a_built_lerobot_dataset_is_calibrated_from_its_own_depth_stream(sim, tmp_path, capsys):
    """``qa calibrate`` on a LeRobot dataset reads the dataset's own depth (here the colour-coded depth stream an
    imac build wrote, lossless), with no --depth da3: the head camera comes back within its goal."""
    import yaml

    from imac_data.core.cameras import save_calibration

    src, truth = sim
    save_calibration(tmp_path / "truth.json", truth)
    recipe = {"name": "calib_from_dataset", "task": "transfer the cube", "robot": {"platform": "aloha_sim"},
              "source": {"type": "aloha_hdf5", "path": str(src), "episodes": 1},
              "cameras": {"calibration": str(tmp_path / "truth.json")},
              "augment": {"height": HW[0], "width": HW[1], "contact_chunk": 8}}
    (tmp_path / "build.yaml").write_text(yaml.safe_dump(recipe))
    root = tmp_path / "dataset"
    assert imac_main(["build", "--repo", "local/calib_from_dataset", "--recipe", str(tmp_path / "build.yaml"),
                      "--root", str(root), "--no-progress", "--workers", "1"]) == 0, capsys.readouterr().err
    out = tmp_path / "calib.json"
    assert imac_main(["qa", "calibrate", str(root), "--recipe", str(ALOHA_RECIPE), "--out", str(out), "--cameras",
                      "cam_high", "--fov", f"cam_high={ALOHA_FOVY['cam_high'] * 1.15}", "--near", str(ALOHA_NEAR),
                      "--refine", "none", "--no-progress"]) == 0, capsys.readouterr().err
    t, r = error(truth["cam_high"], load_calibration(out)["cam_high"])
    assert t <= 3.0 and r <= 0.3, (t, r)


def test_a_focal_length_far_from_its_start_is_refused_with_the_joint_units_named_first():
    """The focal bound (``FOCAL_SPAN``): a pose that needs a focal length more than twice (or less than half) its
    start is a robot posed wrongly; the refusal names the joint map's units before the depth's and --fov."""
    start, principal = 400.0, (240.0, 320.0)
    for ratio in (0.51, 1.0, 1.99):
        res = CameraResult("cam", np.eye(4), start * ratio, 1.0)
        assert _plausible("cam", res, start, principal) is res
    for ratio in (0.45, 2.1, 56.0):
        with pytest.raises(CalibrationRefused, match=r"times its start of 400 px") as refused:
            _plausible("cam", CameraResult("cam", np.eye(4), start * ratio, 1.0), start, principal)
        message = str(refused.value)
        assert message.index("joint map's units") < message.index("depth's units") < message.index("--fov")
