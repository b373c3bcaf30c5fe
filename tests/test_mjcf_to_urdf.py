"""MJCF -> URDF export, checked against MuJoCo itself (the oracle).

A small synthetic model covers what gym-aloha's arms do not: several joints on
one body, joint anchors and reference positions, primitives, materials, hidden
geoms and a non-uniformly scaled, off-centre mesh. The ALOHA meshes are checked
link-locally here (STL file + URDF visual origin == MuJoCo's compiled vertices);
the posed checks live in test_robot.py.
"""

from __future__ import annotations

import io
import math

import mujoco
import numpy as np
import pytest
import torch
import trimesh
import yourdfpy

from imac_data.core.robot.mjcf import export_urdf, mat_to_rpy, mesh_file, write_urdf
from imac_data.core.robot.model import RobotConfig, RobotModel
from imac_data.errors import InputError

TOL = 1e-5  # metres / rotation-matrix entries (~rad)

SYNTH_XML = """
<mujoco>
  <compiler angle="radian"/>
  <asset>
    <mesh name="blob" file="blob.stl" scale="0.5 1 2"/>
    <material name="green" rgba="0 1 0 1"/>
  </asset>
  <worldbody>
    <body name="table" pos="0 0 -0.1"><geom type="box" size="1 1 0.05"/></body>
    <body name="mount" pos="0.3 0 0.2" euler="0 0 0.4">
      <body name="bot/base" pos="0.1 -0.2 0.05" quat="0.9 0.1 0.3 -0.2">
        <geom name="bot/base_box" type="box" size="0.05 0.04 0.03" pos="0.01 0 0.02" material="green"/>
        <geom name="bot/hidden" type="capsule" size="0.01 0.05" group="3"/>
        <geom name="bot/invisible" type="sphere" size="0.02" rgba="1 0 0 0"/>
        <body name="bot/link1" pos="0 0 0.1" euler="0.2 -0.1 0.3">
          <joint name="bot/j1" type="hinge" axis="0 0.6 0.8" pos="0.02 0.01 -0.03" ref="0.3" range="-2 2"/>
          <geom name="bot/blob" type="mesh" mesh="blob" pos="0.03 0 0.05" euler="0.5 1.5707963267948966 0"
                rgba="0.2 0.3 0.4 1"/>
          <body name="bot/link2" pos="0.2 0 0">
            <joint name="bot/j2a" type="hinge" axis="1 0 0" pos="0 0.02 0"/>
            <joint name="bot/j2b" type="slide" axis="0 0 1" range="-0.1 0.1" ref="0.01"/>
            <joint name="bot/j2c" type="hinge" axis="0 1 0" pos="0.01 0 0" range="-1 1"/>
            <geom name="bot/ball" type="sphere" size="0.03" pos="0.05 0 0" rgba="1 1 0 1"/>
            <body name="bot/finger" pos="0.1 0 0">
              <joint name="bot/slide" type="slide" axis="0 1 0" range="0 0.05"/>
              <geom name="bot/cyl" type="cylinder" size="0.01 0.04" quat="0.70710678 0.70710678 0 0"/>
            </body>
          </body>
        </body>
      </body>
    </body>
    <body name="cube" pos="0 0.5 0.1"><freejoint/><geom type="box" size="0.02 0.02 0.02"/></body>
  </worldbody>
</mujoco>
"""

SYNTH_JOINTS = ("bot/j1", "bot/j2a", "bot/j2b", "bot/j2c", "bot/slide")


def _rot(axis, angle):
    R = np.empty(9)
    q = np.empty(4)
    axis = np.asarray(axis, float)
    mujoco.mju_axisAngle2Quat(q, axis / np.linalg.norm(axis), angle)
    mujoco.mju_quat2Mat(R, q)
    return R.reshape(3, 3)


@pytest.fixture(scope="module")
def synth(tmp_path_factory):
    d = tmp_path_factory.mktemp("synth")
    # An off-centre, rotated, asymmetric mesh so MuJoCo's re-centring is non-trivial.
    blob = trimesh.creation.box(extents=(0.06, 0.03, 0.01))
    blob.vertices[0] += (0.004, -0.002, 0.003)  # break the symmetry
    blob.apply_transform(trimesh.transformations.rotation_matrix(0.7, (1, 2, 3), point=(0, 0, 0)))
    blob.apply_translation((0.05, -0.02, 0.01))
    blob.export(d / "blob.stl")
    (d / "synth.xml").write_text(SYNTH_XML)
    model = mujoco.MjModel.from_xml_path(str(d / "synth.xml"))
    urdf_path = write_urdf(d / "synth.urdf", model, ["bot/base"], mesh_dir=d,
                           mimic={"bot/slide": ("bot/j2b", -0.5, 0.02)})
    robot = RobotModel(RobotConfig("synth", urdf_path, SYNTH_JOINTS[:-1]))
    return model, urdf_path, robot


def _random_qpos(model, rng, joints):
    data = mujoco.MjData(model)
    for name in joints:
        j = model.joint(name).id
        lo, hi = model.jnt_range[j] if model.jnt_limited[j] else (-math.pi, math.pi)
        data.qpos[model.jnt_qposadr[j]] = rng.uniform(lo, hi)
    mujoco.mj_kinematics(model, data)
    return data


def test_export_structure(synth):
    model, urdf_path, robot = synth
    urdf = yourdfpy.URDF.load(str(urdf_path), build_scene_graph=False, load_meshes=False)
    links = set(urdf.link_map)
    assert {"world", "bot/base", "bot/link1", "bot/link2", "bot/finger"} <= links
    assert not {"table", "cube", "mount"} & links  # only the chosen subtree
    joints = urdf.joint_map
    assert joints["bot/j1"].type == "revolute" and joints["bot/j2a"].type == "continuous"
    assert joints["bot/j2b"].type == "prismatic"
    assert (joints["bot/j1"].limit.lower, joints["bot/j1"].limit.upper) == (-2.0, 2.0)
    m = joints["bot/slide"].mimic
    assert (m.joint, m.multiplier, m.offset) == ("bot/j2b", -0.5, 0.02)
    # hidden (group 3) and fully transparent geoms are not exported
    names = {v.name for link in urdf.robot.links for v in link.visuals}
    assert names == {"bot/base_box", "bot/blob", "bot/ball", "bot/cyl"}


def test_fk_matches_mujoco_synthetic(synth):
    """Several joints per body, anchors (jnt_pos), references (qpos0), slides: body poses agree."""
    model, _, robot = synth
    rng = np.random.default_rng(1)
    datas = [_random_qpos(model, rng, SYNTH_JOINTS) for _ in range(20)]
    values = {n: torch.tensor([d.qpos[model.joint(n).qposadr[0]] for d in datas], dtype=torch.float64)
              for n in SYNTH_JOINTS}
    poses = robot.forward_kinematics_joints(values)
    for body in ("bot/base", "bot/link1", "bot/link2", "bot/finger"):
        b = model.body(body).id
        T = poses[body].numpy()
        np.testing.assert_allclose(T[:, :3, 3], [d.xpos[b] for d in datas], atol=TOL, err_msg=body)
        np.testing.assert_allclose(T[:, :3, :3], [d.xmat[b].reshape(3, 3) for d in datas], atol=TOL, err_msg=body)


def test_mimic_follows_leader(synth):
    model, _, robot = synth
    q = torch.tensor([0.1, 0.2, 0.03, -0.4], dtype=torch.float64)
    th = dict(zip(robot.joint_names, robot.joint_positions(q)))
    assert th["bot/slide"].item() == pytest.approx(0.02 - 0.5 * 0.03)
    # the oracle: MuJoCo with the follower set by the same rule
    data = mujoco.MjData(model)
    for name, v in zip(SYNTH_JOINTS, [0.1, 0.2, 0.03, -0.4, 0.02 - 0.5 * 0.03]):
        data.qpos[model.joint(name).qposadr[0]] = v
    mujoco.mj_kinematics(model, data)
    T = robot.link_poses(q)["bot/finger"].numpy()
    np.testing.assert_allclose(T[:3, 3], data.xpos[model.body("bot/finger").id], atol=TOL)


def test_visual_geometry_matches_mujoco_synthetic(synth):
    model, _, robot = synth
    data = _random_qpos(model, np.random.default_rng(2), SYNTH_JOINTS)
    values = {n: torch.tensor(data.qpos[model.joint(n).qposadr[0]], dtype=torch.float64) for n in SYNTH_JOINTS}
    poses = robot.forward_kinematics_joints(values)
    posed = robot.posed_vertices(link_poses=poses)
    by_name = {m.name: (m, v.numpy()) for m, v in zip(robot.visual_meshes, posed)}
    for name, (mesh, v) in by_name.items():
        g = model.geom(name).id
        R, p = data.geom_xmat[g].reshape(3, 3), data.geom_xpos[g]
        local = (v - p) @ R  # our posed vertices in MuJoCo's geom frame
        size = model.geom_size[g]
        if name == "bot/blob":  # mesh: vertex for vertex
            mid = model.geom_dataid[g]
            ref = model.mesh_vert[model.mesh_vertadr[mid]:model.mesh_vertadr[mid] + model.mesh_vertnum[mid]]
            assert local.shape == ref.shape
            np.testing.assert_allclose(local, ref, atol=TOL)
        elif name == "bot/base_box":  # corners at +-half size
            np.testing.assert_allclose(np.abs(local), np.broadcast_to(size, local.shape), atol=TOL)
        elif name == "bot/ball":
            np.testing.assert_allclose(np.linalg.norm(local, axis=1), size[0], atol=TOL)
        elif name == "bot/cyl":  # axis = geom z, caps at +-half length
            np.testing.assert_allclose(np.abs(local[:, 2]), size[1], atol=TOL)
            assert np.linalg.norm(local[:, :2], axis=1).max() == pytest.approx(size[0], abs=TOL)
        expected_rgba = model.mat_rgba[model.geom_matid[g]] if name == "bot/base_box" else model.geom_rgba[g]
        np.testing.assert_allclose(mesh.rgba, expected_rgba, atol=1e-6)


def test_aloha_mesh_origins_undo_recentring():
    """STL vertices * scale, through the URDF visual origin == MuJoCo's compiled vertices
    placed with geom_pos/geom_quat (both in the body frame), for every ALOHA mesh geom."""
    from gym_aloha.constants import ASSETS_DIR

    model = mujoco.MjModel.from_xml_path(str(ASSETS_DIR / "bimanual_viperx_transfer_cube.xml"))
    text = export_urdf(model, ["vx300s_left", "vx300s_right"], mesh_dir=ASSETS_DIR)
    urdf = yourdfpy.URDF.load(io.BytesIO(text.encode()), build_scene_graph=False, load_meshes=False)
    visuals = {v.name: v for link in urdf.robot.links for v in link.visuals}
    n_checked = 0
    for g in range(model.ngeom):
        if model.geom_type[g] != mujoco.mjtGeom.mjGEOM_MESH or model.geom(g).name not in visuals:
            continue
        vis = visuals[model.geom(g).name]
        m = model.geom_dataid[g]
        assert vis.geometry.mesh.filename == str((ASSETS_DIR / mesh_file(model, m)).resolve())
        v_file = trimesh.load(vis.geometry.mesh.filename, force="mesh").vertices * vis.geometry.mesh.scale
        ours = v_file @ vis.origin[:3, :3].T + vis.origin[:3, 3]
        ref = model.mesh_vert[model.mesh_vertadr[m]:model.mesh_vertadr[m] + model.mesh_vertnum[m]]
        R = np.empty(9)
        mujoco.mju_quat2Mat(R, model.geom_quat[g])
        ref = ref @ R.reshape(3, 3).T + model.geom_pos[g]
        assert ours.shape == ref.shape
        np.testing.assert_allclose(ours, ref, atol=1e-6, err_msg=model.geom(g).name)
        n_checked += 1
    assert n_checked == 22  # 11 mesh geoms per arm


def test_rpy_round_trip_including_gimbal_lock():
    rng = np.random.default_rng(3)
    mats = [_rot(rng.normal(size=3), rng.uniform(-math.pi, math.pi)) for _ in range(200)]
    mats += [_rot((0, 1, 0), s * math.pi / 2) @ _rot((1, 0, 0), 0.3) for s in (-1, 1)]
    mats += [_rot((0, 1, 0), math.pi / 2 - 1e-10) @ _rot((0, 0, 1), 0.7)]
    for R in mats:
        mat_to_rpy(R)  # asserts the round trip to 1e-9 internally


def _model(xml):
    return mujoco.MjModel.from_xml_string(xml)


def test_refuses_what_urdf_cannot_express(tmp_path):
    capsule = _model('<mujoco><worldbody><body name="r"><geom type="capsule" size="0.01 0.1"/></body>'
                     '</worldbody></mujoco>')
    with pytest.raises(InputError, match="CAPSULE"):
        export_urdf(capsule, ["r"])
    free = _model('<mujoco><worldbody><body name="r"><freejoint name="f"/><geom size="0.1"/></body>'
                  '</worldbody></mujoco>')
    with pytest.raises(InputError, match="ball or free"):
        export_urdf(free, ["r"])
    moving_parent = _model('<mujoco><worldbody><body name="p"><joint name="h"/><geom size="0.1"/>'
                           '<body name="r"><geom size="0.1"/></body></body></worldbody></mujoco>')
    with pytest.raises(InputError, match="ancestor 'p'"):
        export_urdf(moving_parent, ["r"])
    with pytest.raises(InputError, match="no body 'nope'"):
        export_urdf(capsule, ["nope"])
    two = _model('<mujoco><worldbody><body name="r"><joint name="a"/><geom size="0.1"/></body>'
                 '</worldbody></mujoco>')
    with pytest.raises(InputError, match="mimic"):
        export_urdf(two, ["r"], mimic={"a": ("missing", 1.0, 0.0)})


def test_missing_mesh_file_is_named(tmp_path):
    trimesh.creation.box().export(tmp_path / "m.stl")
    xml = ('<mujoco><asset><mesh name="m" file="m.stl"/></asset><worldbody><body name="r">'
           '<geom type="mesh" mesh="m"/></body></worldbody></mujoco>')
    (tmp_path / "r.xml").write_text(xml)
    model = mujoco.MjModel.from_xml_path(str(tmp_path / "r.xml"))
    with pytest.raises(InputError, match="pass mesh_dir"):
        export_urdf(model, ["r"])
    with pytest.raises(InputError, match=r"elsewhere.*m\.stl"):
        export_urdf(model, ["r"], mesh_dir=tmp_path / "elsewhere")
