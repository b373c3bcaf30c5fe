"""The rig: one robot + cameras + controller, from a recipe or from a built dataset alone.

Oracles: the recipe's own rig (FK, renders, controller) for the dataset round trip; the
analytic degrees -> radians conversion for per-entry affine joint maps; file hashes for
the robot description carried by the dataset.
"""

import json
import math
import shutil

import numpy as np
import pytest
import torch
import yaml

from imac_data import aloha
from imac_data.errors import InputError
from imac_data.ingest import IngestOptions, ingest_episodes
from imac_data.recipes import RECIPES_DIR, load_recipe, parse_recipe
from imac_data.rig import Rig
from imac_data.robot import JointEntry, RobotConfig, RobotModel
from imac_data.robot_files import DESCRIPTION_DIR, packaged_description
from imac_data.simulate import SimConfig, record_dataset


@pytest.fixture(scope="module")
def sim_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("rig_sim")
    record_dataset(SimConfig(num_episodes=1, width=80, height=60, max_steps=8), out, progress=False)
    return out


@pytest.fixture(scope="module")
def recipe_rig(sim_dir):
    return Rig.from_recipe(load_recipe(RECIPES_DIR / "aloha_sim_transfer_cube.yaml"), sim_dir / "calibration.json")


@pytest.fixture(scope="module")
def base(sim_dir, recipe_rig, tmp_path_factory):
    root = tmp_path_factory.mktemp("rig_ds") / "ds"
    ingest_episodes(sorted(sim_dir.glob("episode_*.hdf5")), rig=recipe_rig, repo_id="local/rig", root=root,
                    options=IngestOptions(fps=25, task="t", state_names=aloha.STATE_NAMES), progress=False)
    return root


def test_dataset_rebuilds_the_rig_exactly(base, recipe_rig):
    """Rig.from_info on the dataset alone = the recipe's rig: the same info block, FK,
    renders, gripper samples and controller."""
    info = json.loads((base / "meta" / "info.json").read_text())
    block = info["imac"]
    assert block["schema_version"] == 1
    rig = Rig.from_info(info, base)
    assert rig.to_info() == {k: block[k] for k in ("robot", "cameras", "controller", "gripper_surface")}
    assert rig.to_info() == recipe_rig.to_info()  # the recipe's calibration is at the image size here
    assert rig.robot.config.urdf_path.is_relative_to(base / DESCRIPTION_DIR)
    q = torch.randn(6, rig.dof, dtype=torch.float64) * 0.5
    a, b = recipe_rig.link_poses(q), rig.link_poses(q)
    assert all(torch.equal(a[k], b[k]) for k in a)
    va, vb = recipe_rig.robot_views(q[:2], resolution=(30, 40)), rig.robot_views(q[:2], resolution=(30, 40))
    for name in ("rgb", "mask", "depth", "link_id", "T_world_cam", "gripper_points"):
        assert torch.equal(getattr(va, name), getattr(vb, name)), name
    action = np.random.default_rng(0).normal(size=(5, rig.dof))
    np.testing.assert_array_equal(recipe_rig.rollout(q[0].numpy(), action), rig.rollout(q[0].numpy(), action))
    assert rig.state_names == aloha.STATE_NAMES


def test_description_is_complete_and_checked(base, tmp_path, recipe_rig):
    desc = json.loads((base / "meta" / "info.json").read_text())["imac"]["robot"]["description"]
    files = sorted(p.relative_to(base / DESCRIPTION_DIR).as_posix() for p in (base / DESCRIPTION_DIR).rglob("*")
                   if p.is_file())
    assert files == sorted(["robot.urdf", *desc["files"]])
    assert desc["bytes"] == sum((base / DESCRIPTION_DIR / f).stat().st_size for f in files)
    # packaging the packaged description changes nothing (the round trip's fixed point)
    text, _ = packaged_description(Rig.from_dataset(base).robot)
    assert text == (base / DESCRIPTION_DIR / "robot.urdf").read_text()
    damaged = tmp_path / "damaged"
    shutil.copytree(base, damaged)
    mesh = damaged / DESCRIPTION_DIR / next(iter(desc["files"]))
    mesh.write_bytes(mesh.read_bytes()[:-10])
    with pytest.raises(InputError, match=mesh.name):
        Rig.from_dataset(damaged)
    mesh.unlink()
    with pytest.raises(InputError, match="missing"):
        Rig.from_dataset(damaged)


def test_every_joint_entry_may_carry_an_affine_map():
    """Arm joints recorded in degrees, the gripper in -100..100: the same link poses as the
    radians / metres vector (analytic conversion as the oracle)."""
    config = aloha.robot_config()
    robot = RobotModel(config)
    entries = []
    for i in range(config.dof):
        e = config.joint_entry(i)
        if e.is_identity:  # arm joint: degrees
            entries.append({"joint": e.joint, "scale": math.pi / 180})
        else:  # gripper: -100..100 -> the normalised 0..1 of the original map
            entries.append({"joint": e.joint, "scale": e.scale / 200, "offset": e.offset + e.scale / 2})
    deg = RobotModel(RobotConfig("deg", config.urdf_path, RobotConfig.parse_joint_map(entries), config.gripper_links,
                                 config.package_dirs))
    q = torch.rand(4, config.dof, dtype=torch.float64)
    grip = [i for i in range(config.dof) if not config.joint_entry(i).is_identity]
    q_units = q * 180 / math.pi
    q_units[:, grip] = q[:, grip] * 200 - 100
    a, b = robot.link_poses(q), deg.link_poses(q_units)
    assert max(float((a[k] - b[k]).abs().max()) for k in a) < 1e-9
    # the recipe forms: a name, {joint, scale, offset}, and the older {gripper, scale, offset}
    parsed = RobotConfig.parse_joint_map(["a", {"joint": "b", "scale": 2.0}, {"gripper": "c", "scale": 1.0,
                                                                                "offset": 0.5}])
    assert parsed == ("a", JointEntry(1, "b", 2.0), JointEntry(2, "c", 1.0, 0.5))
    assert RobotConfig.parse_joint_map([{"joint": "b", "scale": 1.0}]) == ("b",)  # identity stays a name
    with pytest.raises(InputError, match=r"joint_map\[1\]"):
        RobotConfig.parse_joint_map(["a", {"joint": "b", "scale": 0.0}])
    with pytest.raises(InputError, match=r"joint_map\[0\]"):
        RobotConfig.parse_joint_map([{"joint": "b", "units": "deg"}])


def test_recipe_joint_map_and_controller_sections(tmp_path, sim_dir):
    config = aloha.robot_config()
    data = {"name": "custom", "task": "t", "fps": 25,
            "robot": {"urdf": str(config.urdf_path), "gripper_links": list(config.gripper_links),
                      "package_dirs": {k: str(v) for k, v in config.package_dirs},
                      "joint_map": config.joint_map_dict(),
                      "controller": {"mode": "delta", "grippers": [{"index": 6, "low": 0.0, "high": 1.0}]}},
            "cameras": {"calibration": str(sim_dir / "calibration.json")},
            "source": {"type": "aloha_hdf5", "path": str(sim_dir)}}
    path = tmp_path / "custom.yaml"
    path.write_text(yaml.safe_dump(data))
    rig = Rig.from_recipe(load_recipe(path))
    assert rig.robot.config.joint_map == config.joint_map
    assert rig.controller.mode == "delta" and rig.controller.grippers[0].high == 1.0
    bad = dict(data, robot={**data["robot"], "controller": {"mode": "delta", "grippers": [{"index": 40}]}})
    with pytest.raises(InputError, match="index 40 out of range"):
        parse_recipe(bad, str(path))
    with pytest.raises(InputError, match="brings its own robot"):
        parse_recipe({**data, "robot": {"platform": "aloha_sim", "joint_map": ["x"]}}, str(path))


def test_contact_from_predicted_depth_has_a_batch_axis(recipe_rig, sim_dir):
    """Rig.contact on a batch of depth maps = one call per item (what a world model rollout does)."""
    from imac_data.aloha_hdf5 import read_episode

    ep = read_episode(sorted(sim_dir.glob("episode_*.hdf5"))[0])
    depth = torch.stack([torch.as_tensor(ep.depth_mm[n][:2].astype(np.float32) / 1000) for n in recipe_rig.names],
                        1)  # (2, V, 60, 80)
    q = torch.as_tensor(ep.qpos[:4], dtype=torch.float32)
    batched = recipe_rig.contact(depth, q[:2], torch.stack([q[1:3], q[2:4]]))
    single = recipe_rig.contact(depth[1], q[1], q[2:4])
    assert batched.r2s_rgb.shape == (2, 2, 3, 60, 80, 3) and batched.caps.shape == (2, 2)
    assert torch.equal(batched.r2s_rgb[1], single.r2s_rgb) and torch.equal(batched.caps[1], single.caps)
    with pytest.raises(InputError, match="reference depth"):
        recipe_rig.contact(depth[0, :2], q[0], q[1:3])
