"""RobotModel on the exported ALOHA URDF, with MuJoCo as the oracle.

MuJoCo's own kinematics (``mj_kinematics``: body poses, geom poses, compiled
mesh vertices) is the reference; gym-aloha's own gripper helpers set MuJoCo's
fingers, so the dataset-vector path is checked against code we did not write.
"""

from __future__ import annotations

import os
import shutil

import mujoco
import numpy as np
import pytest
import torch
from gym_aloha.constants import unnormalize_puppet_gripper_position

from imac_data.core.robot import aloha
from imac_data.core.robot.model import GripperMap, RobotConfig, RobotModel
from imac_data.errors import InputError

TOL = 1e-5  # m, and rotation-matrix entries (~rad)
N_CONFIGS = 64


@pytest.fixture(scope="module")
def cache_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("imac_cache")


@pytest.fixture(scope="module")
def config(cache_dir):
    return aloha.robot_config(cache_dir)


@pytest.fixture(scope="module")
def robot(config):
    return RobotModel(config)


@pytest.fixture(scope="module", params=aloha.TASKS)
def mj_model(request):
    return mujoco.MjModel.from_xml_path(str(aloha.mjcf_path(request.param)))


def _robot_bodies(model, robot):
    return [b for b in range(1, model.nbody) if model.body(b).name in robot.link_names]


def _random_raw_configs(model, robot, n, seed):
    """n MuJoCo states with every robot hinge/slide uniform in its range (fingers independent)."""
    rng = np.random.default_rng(seed)
    datas = []
    for _ in range(n):
        d = mujoco.MjData(model)
        for name in robot.joint_names:
            j = model.joint(name).id
            d.qpos[model.jnt_qposadr[j]] = rng.uniform(*model.jnt_range[j])
        mujoco.mj_kinematics(model, d)
        datas.append(d)
    return datas


def _assert_poses(poses, datas, bodies, model):
    for b in bodies:
        name = model.body(b).name
        T = poses[name].detach().cpu().double().numpy().reshape(len(datas), 4, 4)
        np.testing.assert_allclose(T[:, :3, 3], [d.xpos[b] for d in datas], atol=TOL, err_msg=name)
        np.testing.assert_allclose(T[:, :3, :3], [d.xmat[b].reshape(3, 3) for d in datas], atol=TOL,
                                   err_msg=name)
        np.testing.assert_allclose(T[:, 3], np.broadcast_to([0, 0, 0, 1], (len(datas), 4)), atol=0)


def _dataset_vector(rng, n, model):
    """Random gym-aloha qpos/action vectors: arm joints in range, grippers in [0, 1]."""
    q = np.empty((n, 14))
    for k, arm in enumerate(aloha.ARMS):
        for i, j in enumerate(aloha.ARM_JOINTS):
            q[:, 7 * k + i] = rng.uniform(*model.jnt_range[model.joint(f"{arm}/{j}").id], size=n)
        q[:, 7 * k + 6] = rng.uniform(0, 1, size=n)
    return q


def _mujoco_from_dataset_vector(model, q):
    """gym-aloha's own rule: left finger = unnormalize(g), right finger = -left finger."""
    datas = []
    for row in q:
        d = mujoco.MjData(model)
        for k, arm in enumerate(aloha.ARMS):
            for i, j in enumerate(aloha.ARM_JOINTS):
                d.qpos[model.joint(f"{arm}/{j}").qposadr[0]] = row[7 * k + i]
            finger = unnormalize_puppet_gripper_position(row[7 * k + 6])
            d.qpos[model.joint(f"{arm}/left_finger").qposadr[0]] = finger
            d.qpos[model.joint(f"{arm}/right_finger").qposadr[0]] = -finger
        mujoco.mj_kinematics(model, d)
        datas.append(d)
    return datas


# ----------------------------------------------------------------------------- kinematics


def test_structure(robot, config):
    assert robot.dof == 14 and config.dof == 14
    assert len(robot.joint_names) == 16  # 2 x (6 arm + 2 fingers)
    assert robot.mimic == {f"{a}/right_finger": (f"{a}/left_finger", -1.0, 0.0) for a in aloha.ARMS}
    assert robot.link_names[0] == "world"
    assert {"vx300s_left/gripper_link", "vx300s_right/gripper_link"} <= set(robot.link_names)
    assert set(robot.gripper_links) <= set(robot.link_names)
    assert all(isinstance(config.joint_map[i], GripperMap) for i in (6, 13))


def test_fk_raw_joints_match_mujoco(robot, mj_model):
    datas = _random_raw_configs(mj_model, robot, N_CONFIGS, seed=0)
    values = {n: torch.tensor([d.qpos[mj_model.joint(n).qposadr[0]] for d in datas], dtype=torch.float64)
              for n in robot.joint_names}
    poses = robot.forward_kinematics_joints(values)
    bodies = _robot_bodies(mj_model, robot)
    assert len(bodies) == len(robot.link_names) - 1  # every exported link is a MuJoCo body (+ world)
    _assert_poses(poses, datas, bodies, mj_model)


def test_fk_dataset_vector_matches_mujoco(robot, mj_model):
    q = _dataset_vector(np.random.default_rng(1), N_CONFIGS, mj_model)
    poses = robot.link_poses(torch.tensor(q, dtype=torch.float64))
    _assert_poses(poses, _mujoco_from_dataset_vector(mj_model, q), _robot_bodies(mj_model, robot), mj_model)


def test_gripper_map_is_gym_alohas(robot):
    q = torch.zeros(14, dtype=torch.float64)
    q[6], q[13] = 1.0, 0.25
    th = dict(zip(robot.joint_names, robot.joint_positions(q).tolist()))
    assert th["vx300s_left/left_finger"] == pytest.approx(unnormalize_puppet_gripper_position(1.0), abs=1e-12)
    assert th["vx300s_left/right_finger"] == pytest.approx(-unnormalize_puppet_gripper_position(1.0), abs=1e-12)
    assert th["vx300s_right/left_finger"] == pytest.approx(unnormalize_puppet_gripper_position(0.25), abs=1e-12)
    assert th["vx300s_right/waist"] == 0.0


def test_visual_meshes_match_mujoco_geoms(robot, mj_model):
    """Our posed visual vertices == MuJoCo's compiled mesh vertices placed at geom_xpos/geom_xmat."""
    q = _dataset_vector(np.random.default_rng(2), 3, mj_model)
    datas = _mujoco_from_dataset_vector(mj_model, q)
    posed = robot.posed_vertices(torch.tensor(q, dtype=torch.float64))
    m = mj_model
    robot_geoms = [g for g in range(m.ngeom)
                   if m.body(m.geom_bodyid[g]).name in robot.link_names and m.geom_group[g] < 3]
    assert sorted(mesh.name for mesh in robot.visual_meshes) == sorted(m.geom(g).name for g in robot_geoms)
    for mesh, v in zip(robot.visual_meshes, posed):
        g = m.geom(mesh.name).id
        mid = m.geom_dataid[g]
        local = m.mesh_vert[m.mesh_vertadr[mid]:m.mesh_vertadr[mid] + m.mesh_vertnum[mid]].astype(np.float64)
        ref = np.stack([local @ d.geom_xmat[g].reshape(3, 3).T + d.geom_xpos[g] for d in datas])
        assert v.shape == ref.shape, mesh.name
        np.testing.assert_allclose(v.numpy(), ref, atol=TOL, err_msg=mesh.name)
        assert mesh.link == m.body(m.geom_bodyid[g]).name
        assert mesh.vertices.dtype == np.float32 and mesh.faces.dtype == np.int32
        assert mesh.faces.min() >= 0 and mesh.faces.max() < len(mesh.vertices)
        assert len(mesh.faces) == m.mesh_facenum[mid]
        np.testing.assert_allclose(mesh.rgba, m.geom_rgba[g], atol=1e-6)


# ----------------------------------------------------------------------------- batching / devices


def test_batch_shapes_agree(robot):
    rng = np.random.default_rng(3)
    q = torch.tensor(rng.uniform(-1, 1, size=(5, 4, 14)))
    q[..., [6, 13]] = q[..., [6, 13]].abs()
    full = robot.link_poses(q)  # (T, B, D)
    flat = robot.link_poses(q.reshape(20, 14))  # (B, D)
    single = robot.link_poses(q[2, 3])  # (D,)
    for name in robot.link_names:
        assert full[name].shape == (5, 4, 4, 4) and single[name].shape == (4, 4)
        torch.testing.assert_close(full[name].reshape(20, 4, 4), flat[name], rtol=0, atol=1e-12)
        torch.testing.assert_close(full[name][2, 3], single[name], rtol=0, atol=1e-12)
    verts = robot.posed_vertices(q)
    assert verts[0].shape == (5, 4, len(robot.visual_meshes[0].vertices), 3)


def test_float32_close_to_float64(robot):
    q = torch.tensor(np.random.default_rng(4).uniform(0, 1, size=(8, 14)))
    p64, p32 = robot.link_poses(q), robot.link_poses(q.float())
    for name in robot.link_names:
        assert p32[name].dtype == torch.float32
        torch.testing.assert_close(p32[name].double(), p64[name], rtol=0, atol=1e-5)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_matches_cpu(robot):
    q = torch.tensor(np.random.default_rng(5).uniform(0, 1, size=(3, 7, 14)))
    cpu = robot.link_poses(q)
    for dtype, atol in ((torch.float64, 1e-12), (torch.float32, 1e-5)):
        gpu = robot.link_poses(q.to("cuda", dtype))
        for name in robot.link_names:
            assert gpu[name].device.type == "cuda" and gpu[name].dtype == dtype
            torch.testing.assert_close(gpu[name].cpu().double(), cpu[name], rtol=0, atol=atol)
    verts = robot.posed_vertices(q.cuda())
    torch.testing.assert_close(verts[0].cpu(), robot.posed_vertices(q)[0], rtol=0, atol=1e-12)


# ----------------------------------------------------------------------------- bad input


def test_wrong_dimension_is_refused(robot):
    with pytest.raises(InputError, match="14 entries.*shape \\(2, 13\\)"):
        robot.link_poses(torch.zeros(2, 13))
    with pytest.raises(InputError, match="14 entries"):
        robot.link_poses(torch.tensor(0.0))


def test_nan_joint_is_named(robot):
    q = torch.zeros(3, 14)
    q[1, 9] = float("nan")
    with pytest.raises(InputError, match=r"joint index 9 \('vx300s_right/elbow'\).*batch position \(1,\)"):
        robot.link_poses(q)
    q = torch.zeros(14)
    q[13] = float("inf")
    with pytest.raises(InputError, match="index 13.*vx300s_right/left_finger"):
        robot.joint_positions(q)
    with pytest.raises(InputError, match="non-finite"):
        robot.forward_kinematics_joints({n: torch.tensor(float("nan")) for n in robot.joint_names})


def test_joint_map_joint_missing_from_urdf(config):
    bad = list(config.joint_map)
    bad[2] = "vx300s_left/elbowz"
    cfg = RobotConfig("aloha", config.urdf_path, tuple(bad), package_dirs=config.package_dirs)
    with pytest.raises(InputError, match=f"'vx300s_left/elbowz'.*{config.urdf_path.name}"):
        RobotModel(cfg)
    mimic = list(config.joint_map)
    mimic[13] = GripperMap(13, "vx300s_right/right_finger", 1.0)
    with pytest.raises(InputError, match="mimic joint"):
        RobotModel(RobotConfig("aloha", config.urdf_path, tuple(mimic), package_dirs=config.package_dirs))
    with pytest.raises(InputError, match="gripper link 'nope'"):
        RobotModel(RobotConfig("aloha", config.urdf_path, config.joint_map, gripper_links=("nope",),
                               package_dirs=config.package_dirs))


def test_config_validation():
    with pytest.raises(InputError, match="index 3"):
        RobotConfig("r", "x.urdf", ("a", GripperMap(3, "f", 1.0)))
    with pytest.raises(InputError, match="mapped twice"):
        RobotConfig("r", "x.urdf", ("a", "a"))
    with pytest.raises(InputError, match="scale"):
        GripperMap(0, "f", 0.0)
    with pytest.raises(InputError, match="does not exist"):
        RobotModel(RobotConfig("r", "/nonexistent/x.urdf", ("a",)))


def test_missing_mesh_file_is_named(config, tmp_path):
    text = config.urdf_path.read_text()
    assert "vx300s_6_wrist.stl" in text
    broken = tmp_path / "broken.urdf"
    broken.write_text(text.replace("vx300s_6_wrist.stl", "vx300s_6_wrist_MISSING.stl"))
    cfg = RobotConfig("aloha", broken, config.joint_map, package_dirs=config.package_dirs)
    with pytest.raises(InputError, match=r"vx300s_6_wrist_MISSING\.stl.*broken\.urdf"):
        RobotModel(cfg)
    no_pkg = RobotConfig("aloha", config.urdf_path, config.joint_map)  # package:// unresolvable
    with pytest.raises(InputError, match="package 'gym_aloha'"):
        RobotModel(no_pkg)


def _one_mesh_robot(tmp_path, mesh_file: str) -> RobotConfig:
    (tmp_path / "r.urdf").write_text(f"""<robot name="r">
  <link name="base"/>
  <link name="tip"><visual><geometry><mesh filename="{mesh_file}"/></geometry></visual></link>
  <joint name="j" type="revolute"><parent link="base"/><child link="tip"/>
    <axis xyz="0 0 1"/><limit lower="-1" upper="1" effort="1" velocity="1"/></joint>
</robot>""")
    return RobotConfig("r", tmp_path / "r.urdf", ("j",))


def test_collada_unit_is_applied(tmp_path):
    """A Collada file in millimetres (``<unit meter="0.001">``, as CAD exporters write it) is
    scaled to metres, as RViz and Gazebo do; the URDF's own scale multiplies on top.
    Oracle: the box's analytic extents."""
    import trimesh

    text = trimesh.creation.box(extents=(100.0, 40.0, 20.0)).export(file_type="dae")
    text = text.decode() if isinstance(text, bytes) else text
    assert "<up_axis>" in text
    (tmp_path / "mm.dae").write_text(text.replace("<up_axis>", '<unit meter="0.001" name="millimeter"/><up_axis>', 1))
    (mesh,) = RobotModel(_one_mesh_robot(tmp_path, "mm.dae")).visual_meshes
    np.testing.assert_allclose(mesh.vertices.max(0) - mesh.vertices.min(0), [0.1, 0.04, 0.02], rtol=1e-6)
    (tmp_path / "r.urdf").write_text((tmp_path / "r.urdf").read_text().replace('"mm.dae"', '"mm.dae" scale="2 1 1"'))
    (mesh,) = RobotModel(RobotConfig("r", tmp_path / "r.urdf", ("j",))).visual_meshes
    np.testing.assert_allclose(mesh.vertices.max(0) - mesh.vertices.min(0), [0.2, 0.04, 0.02], rtol=1e-6)


def test_mesh_without_faces_and_robot_without_visuals_are_named(tmp_path):
    import trimesh

    from imac_data.core.render import make_renderer

    trimesh.PointCloud(np.random.default_rng(0).random((10, 3))).export(tmp_path / "cloud.ply")
    with pytest.raises(InputError, match=r"cloud\.ply.*has no faces"):
        RobotModel(_one_mesh_robot(tmp_path, "cloud.ply"))
    text = (tmp_path / "r.urdf").read_text()
    (tmp_path / "r.urdf").write_text(text.replace('<visual><geometry><mesh filename="cloud.ply"/></geometry></visual>',
                                                  ""))
    robot = RobotModel(RobotConfig("r", tmp_path / "r.urdf", ("j",)))  # FK alone needs no visuals
    with pytest.raises(InputError, match="'r'.*no visual geometry"):
        make_renderer(robot)


def test_joint_ranges_outside_the_urdf_limits_are_named(tmp_path):
    """Analytic limits: a revolute joint in [-1, 2] rad, a prismatic one in [0, 0.04] m, a
    continuous one (never checked). In range, within the slack, or mapped by the joint map:
    nothing; in degrees or a wrong gripper scale: the index, joint, both ranges and the unit."""
    from imac_data.core.robot.joint_ranges import joint_range_problems
    from imac_data.core.robot.model import JointEntry

    link = '<link name="{0}"><visual><geometry><box size="0.01 0.01 0.01"/></geometry></visual></link>'
    joint = ('<joint name="{0}" type="{1}"><parent link="{2}"/><child link="{3}"/><axis xyz="0 0 1"/>{4}</joint>')
    (tmp_path / "r.urdf").write_text(
        '<robot name="r">' + "".join(link.format(n) for n in "abcd")
        + joint.format("rev", "revolute", "a", "b", '<limit lower="-1" upper="2" effort="1" velocity="1"/>')
        + joint.format("slide", "prismatic", "b", "c", '<limit lower="0" upper="0.04" effort="1" velocity="1"/>')
        + joint.format("spin", "continuous", "c", "d", "") + "</robot>")
    robot = RobotModel(RobotConfig("r", tmp_path / "r.urdf", ("rev", "slide", "spin")))
    assert robot.joint_limits == {"rev": ("revolute", -1.0, 2.0), "slide": ("prismatic", 0.0, 0.04)}
    assert joint_range_problems(robot, [-1.0, 0.0, -100.0], [2.0, 0.04, 100.0]) == []  # continuous: any value
    assert joint_range_problems(robot, [-1.29, -0.0039], [2.29, 0.0439]) == []  # within 10 % of the span
    (rev,) = joint_range_problems(robot, [-1.31, 0.0, 0.0], [1.0, 0.0, 0.0])
    assert rev == "joint vector index 0 ('rev'): recorded -1.31..1, outside the URDF limits -1..2 rad"
    (rev,) = joint_range_problems(robot, [np.degrees(-0.5), 0.0, 0.0], [np.degrees(1.5), 0.04, 0.0])
    assert "recorded -28.648..85.944" in rev and rev.endswith("if it records degrees, give it scale: 0.01745329")
    # a gripper recorded 0..1, mapped by the joint map: fine; without the map: 0..1 m, out of range
    gripper = RobotModel(RobotConfig("r", tmp_path / "r.urdf", ("rev", JointEntry(1, "slide", scale=0.04), "spin")))
    assert joint_range_problems(gripper, [0.0, 0.0, 0.0], [1.0, 1.0, 0.0]) == []
    (slide,) = joint_range_problems(robot, [0.0, 0.0, 0.0], [1.0, 1.0, 0.0])
    assert "index 1 ('slide'): recorded 0..1, outside the URDF limits 0..0.04 m" in slide and "degrees" not in slide
    flipped = RobotModel(RobotConfig("r", tmp_path / "r.urdf", ("rev", JointEntry(1, "slide", scale=-0.04), "spin")))
    (slide,) = joint_range_problems(flipped, [0.0, 0.0, 0.0], [1.0, 1.0, 0.0])  # a negative scale flips the range
    assert "mapped to -0.04..0 m" in slide


# ----------------------------------------------------------------------------- export cache


def test_robot_config_cache(cache_dir, config):
    path = config.urdf_path
    assert path.parent == cache_dir and path.name.startswith("aloha_")
    mtime = path.stat().st_mtime_ns
    again = aloha.robot_config(cache_dir)
    assert again == config and path.stat().st_mtime_ns == mtime  # export skipped
    assert [p.name for p in cache_dir.iterdir()] == [path.name]  # no temp files left behind
    # The URDF references gym-aloha's meshes in place, never copies.
    assert "package://gym_aloha/assets/" in path.read_text()
    # A second cache directory gets byte-identical content (deterministic export).
    other = aloha.robot_config(cache_dir.parent / "other_cache")
    assert other.urdf_path.name == path.name and other.urdf_path.read_bytes() == path.read_bytes()
    shutil.rmtree(other.urdf_path.parent)


def test_default_cache_dir_honours_xdg(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    cfg = aloha.robot_config()
    assert cfg.urdf_path.parent == tmp_path / "imac" / "aloha"
    assert os.path.isfile(cfg.urdf_path)
