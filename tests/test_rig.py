"""The rig: one robot + cameras + controller, from a recipe or from a built dataset alone.

Oracles: the recipe's own rig (FK, renders, controller) for the dataset round trip; the
analytic degrees -> radians conversion for per-entry affine joint maps; file hashes for
the robot description carried by the dataset.
"""

import json
import math
import re
import shutil

import numpy as np
import pytest
import torch
import yaml

from imac_data.build.from_episodes import ingest_episodes
from imac_data.core.contact.workspace import DEFAULT_MARGIN, Workspace, depth_in_range, reach_box
from imac_data.core.depth import DepthCodec
from imac_data.core.rig import Rig
from imac_data.core.robot import aloha
from imac_data.core.robot.description import DESCRIPTION_DIR, packaged_description, write_description
from imac_data.core.robot.model import JointEntry, RobotConfig, RobotModel
from imac_data.dataset.info import RIG_KEYS, SCHEMA_VERSION, imac_block, read_info
from imac_data.dataset.ingest import IngestOptions
from imac_data.errors import InputError
from imac_data.recipes import RECIPES_DIR, load_recipe, parse_recipe
from imac_data.sources.sim import rig as sim_rig
from imac_data.sources.sim.recorder import SimConfig, record_dataset


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
    info = read_info(base)
    block = info["imac"]
    assert block["schema_version"] == SCHEMA_VERSION == 3
    rig = Rig.from_info(info, base)
    assert set(RIG_KEYS) == {"robot", "cameras", "controller", "gripper_surface", "workspace"}
    assert rig.to_info() == {k: block[k] for k in RIG_KEYS}
    assert rig.to_info() == recipe_rig.to_info()  # the recipe's calibration is at the image size here
    assert rig.workspace == recipe_rig.workspace and rig.workspace is not None  # the contact crop
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
    desc = read_info(base)["imac"]["robot"]["description"]
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



def _two_part_robot(root):
    """A two-link URDF whose links use different meshes of one file name (a/part.stl, b/part.stl)."""
    import trimesh

    for sub, size in (("a", 0.1), ("b", 0.05)):
        (root / sub).mkdir(parents=True)
        trimesh.creation.box((size, size, size)).export(root / sub / "part.stl")
    (root / "two.urdf").write_text("""<robot name="two">
  <link name="base"><visual><geometry><mesh filename="a/part.stl"/></geometry></visual></link>
  <link name="tip"><visual><geometry><mesh filename="b/part.stl"/></geometry></visual></link>
  <joint name="j" type="revolute"><parent link="base"/><child link="tip"/><origin xyz="0 0 0.2"/>
    <axis xyz="0 0 1"/><limit lower="-1" upper="1" effort="1" velocity="1"/></joint>
</robot>""")
    return RobotModel(RobotConfig(name="two", urdf_path=root / "two.urdf", joint_map=("j",)))


def test_collision_meshes_travel_when_found_and_are_left_out_when_missing(tmp_path):
    """Oracle: the URDF's own elements. A found collision mesh is copied like a visual one;
    a missing one (or one in an unmapped package) drops its <collision> with a warning,
    and packaging the result again changes nothing (the fixed point)."""
    import xml.etree.ElementTree as ET

    robot = _two_part_robot(tmp_path / "src")
    urdf = robot.config.urdf_path
    urdf.write_text(urdf.read_text()
                    .replace('<link name="base">', '<link name="base"><collision><geometry><mesh filename="a/part.stl"/>'
                             '</geometry></collision>')
                    .replace('<link name="tip">', '<link name="tip"><collision><geometry><mesh filename="gone.stl"/>'
                             '</geometry></collision><collision><geometry><mesh filename="package://nowhere/x.stl"/>'
                             '</geometry></collision>'))
    robot = RobotModel(robot.config)
    packaged = tmp_path / "packaged"
    with pytest.warns(UserWarning) as warned:
        text, files = packaged_description(robot)
        write_description(robot, packaged)
    assert {"collision mesh 'gone.stl' of link 'tip'", "collision mesh 'package://nowhere/x.stl' of link 'tip'"} == {
        m for w in warned for m in re.findall(r"collision mesh '[^']+' of link '\w+'", str(w.message))}
    links = {link.get("name"): link for link in ET.fromstring(text).iter("link")}
    assert len(links["base"].findall("collision")) == 1 and not links["tip"].findall("collision")
    assert len(files) == 2  # a/part.stl is shared by the visual and the collision
    again = RobotModel(RobotConfig(name="two", urdf_path=packaged / "robot.urdf", joint_map=("j",)))
    assert packaged_description(again)[0] == text


def test_meshes_of_one_name_are_packaged_apart_wherever_the_source_lives(tmp_path):
    """Oracle: the source files' bytes. Both meshes are kept, and the packaged URDF is the
    same for two copies of the source tree in different places (builds are reproducible)."""
    text_a, files_a = packaged_description(_two_part_robot(tmp_path / "here"))
    text_b, files_b = packaged_description(_two_part_robot(tmp_path / "elsewhere" / "deeper"))
    assert text_a == text_b and sorted(files_a) == sorted(files_b)
    assert len(files_a) == 2
    by_source = {path.relative_to(tmp_path / "here").as_posix(): rel for rel, path in files_a.items()}
    assert set(by_source) == {"a/part.stl", "b/part.stl"}
    for source, rel in by_source.items():
        assert f'filename="{rel}"' in text_a
        assert files_b[rel].read_bytes() == (tmp_path / "here" / source).read_bytes()

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
    from imac_data.sources.hdf5 import read_episode

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


def test_workspace_in_recipes_and_info(tmp_path, sim_dir, recipe_rig, base):
    """The recipe's augment.contact_workspace: an explicit box and depth range are used as
    given; the default is the robot's reach (+ margin) and the codec's range; bad values name
    the field. Schema 1 blocks (no workspace) still load, as a rig without a crop."""
    ws = recipe_rig.workspace
    assert ws.source.startswith("robot reach") and ws.depth_range == (0.0, 3.736)  # where 'manipulation' saturates
    codec = DepthCodec.preset("manipulation")
    top = torch.as_tensor(codec.decode(codec.encode_uint8(np.array([[[3.9, 8.0, 65.535]]], np.float32))))
    assert not depth_in_range(top, *ws.depth_range).any()  # saturated codes are invalid online too
    assert (ws.min, ws.max) == reach_box(recipe_rig.robot, margin=DEFAULT_MARGIN)
    # every vertex of MuJoCo's own robot meshes, posed by MuJoCo over a recorded episode, lies in the box
    import mujoco

    from imac_data.sources.hdf5 import read_episode

    model = sim_rig.load_mujoco_model("transfer_cube")
    data = mujoco.MjData(model)
    free = {model.jnt_bodyid[j] for j in range(model.njnt) if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE}
    geoms = [g for g in range(model.ngeom) if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH
             and model.geom_bodyid[g] != 0 and model.geom_bodyid[g] not in free]
    assert len(geoms) >= 10
    verts = [model.mesh_vert[model.mesh_vertadr[model.geom_dataid[g]]:][:model.mesh_vertnum[model.geom_dataid[g]]]
             for g in geoms]
    for q14 in read_episode(sorted(sim_dir.glob("episode_*.hdf5"))[0]).qpos:
        sim_rig.set_mujoco_qpos(model, data, q14)
        mujoco.mj_kinematics(model, data)
        world = np.concatenate([v @ data.geom_xmat[g].reshape(3, 3).T + data.geom_xpos[g] for g, v in zip(geoms, verts)])
        assert ws.contains(torch.as_tensor(world)).all()
    config = aloha.robot_config()
    data_yaml = {"name": "custom", "task": "t", "fps": 25,
                 "robot": {"urdf": str(config.urdf_path), "gripper_links": list(config.gripper_links),
                           "package_dirs": {k: str(v) for k, v in config.package_dirs},
                           "joint_map": config.joint_map_dict()},
                 "cameras": {"calibration": str(sim_dir / "calibration.json")},
                 "source": {"type": "aloha_hdf5", "path": str(sim_dir)},
                 "augment": {"depth_codec": "general",
                             "contact_workspace": {"min": [-0.7, 0.0, -0.05], "max": [0.7, 1.2, 0.6],
                                                   "depth_range": [0.05, 2.0]}}}
    path = tmp_path / "custom.yaml"
    path.write_text(yaml.safe_dump(data_yaml))
    rig = Rig.from_recipe(load_recipe(path))
    assert rig.workspace == Workspace((-0.7, 0.0, -0.05), (0.7, 1.2, 0.6), (0.05, 2.0), source="recipe")
    margin = {**data_yaml, "augment": {"depth_codec": "general", "contact_workspace": {"margin": 0.0}}}
    path.write_text(yaml.safe_dump(margin))
    wide = Rig.from_recipe(load_recipe(path)).workspace
    assert wide.depth_range == (0.0, 306.869) and all(a < b for a, b in zip(ws.min, wide.min))  # general; no margin
    for bad, field in [({"min": [0, 0, 0]}, "give both min and max"),
                       ({"min": [0, 0, 0], "max": [1, 1, 1], "margin": 0.1}, r"contact_workspace\.margin"),
                       ({"min": [0, 0], "max": [1, 1, 1]}, r"contact_workspace\.min"),
                       ({"min": [0, 0, 1], "max": [1, 1, 1]}, "min must be below max"),
                       ({"depth_range": [2.0, 1.0]}, r"contact_workspace\.depth_range"),
                       ({"box": 1}, "unknown field")]:
        with pytest.raises(InputError, match=field):
            parse_recipe({**data_yaml, "augment": {"contact_workspace": bad}}, str(path))
    # JSON round trip, an open far end included
    assert Workspace.from_dict(json.loads(json.dumps(Workspace((0, 0, 0), (1, 1, 1), (0.1, math.inf)).to_dict()))) \
        == Workspace((0, 0, 0), (1, 1, 1), (0.1, math.inf))
    # schema 1: no workspace key; the rig loads without a crop; schema 2 requires the key
    info = read_info(base)
    old = {**info, "imac": {k: v for k, v in info["imac"].items() if k != "workspace"}}
    old["imac"]["schema_version"] = 1
    assert Rig.from_info(old, base).workspace is None
    imac_block(old, require=RIG_KEYS)
    with pytest.raises(InputError, match="workspace"):
        imac_block({**old, "imac": {**old["imac"], "schema_version": 2}}, require=RIG_KEYS)


def test_rig_contact_crops_to_its_workspace(recipe_rig, sim_dir):
    """Rig.contact applies the rig's workspace: saturated depth (65.535 m) gives exactly what
    invalid depth (0) gives; with the crop switched off it ruins the caps."""
    from imac_data.sources.hdf5 import read_episode

    ep = read_episode(sorted(sim_dir.glob("episode_*.hdf5"))[0])
    depth = torch.stack([torch.as_tensor(ep.depth_mm[n][0].astype(np.float32) / 1000) for n in recipe_rig.names])
    q = torch.as_tensor(ep.qpos[:3], dtype=torch.float32)
    hit = torch.as_tensor(np.random.default_rng(0).random(depth.shape) < 0.05)
    saturated, invalid = depth.clone(), depth.clone()
    saturated[hit], invalid[hit] = 65.535, 0.0
    a, b = recipe_rig.contact(saturated, q[0], q[1:]), recipe_rig.contact(invalid, q[0], q[1:])
    for name in ("r2s_rgb", "s2g_rgb", "caps"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name
    assert (a.caps <= recipe_rig.workspace.diagonal).all()
    assert float(recipe_rig.contact(saturated, q[0], q[1:], workspace=None).caps[1]) > 10
