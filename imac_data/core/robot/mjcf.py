"""Export robot subtrees of a compiled MuJoCo model to URDF (simulated rigs ship only MJCF).

Working from the *compiled* model, MuJoCo has resolved includes, defaults and mesh
processing, so the URDF describes what MuJoCo simulates: link frames are body frames, hinge
and slide joints become revolute (continuous) and prismatic joints, intermediate links carry
what a URDF joint cannot express, and visual origins undo MuJoCo's mesh re-centring
(``docs/simulation.md``). Ball and free joints, and shapes without a URDF primitive, are refused."""

from __future__ import annotations

import math
import os
import tempfile
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from xml.sax.saxutils import quoteattr

import mujoco
import numpy as np

from imac_data.errors import InputError

WORLD_LINK = "world"
VISIBLE_GROUPS = (0, 1, 2)  # geom groups MuJoCo's viewer/renderer shows by default
_DEFAULT_RGBA = np.array([0.5, 0.5, 0.5, 1.0], dtype=np.float32)

# mimic spec: follower joint -> (leader joint, multiplier, offset)
MimicSpec = Mapping[str, tuple[str, float, float]]


# ----------------------------------------------------------------------------- math


def _quat_to_mat(quat) -> np.ndarray:
    R = np.empty(9)
    mujoco.mju_quat2Mat(R, np.asarray(quat, dtype=np.float64))
    return R.reshape(3, 3)


def _pose(pos, quat) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = _quat_to_mat(quat)
    T[:3, 3] = pos
    return T


def _translation(p) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = p
    return T


def _axis_angle(axis, angle: float) -> np.ndarray:
    quat = np.empty(4)
    mujoco.mju_axisAngle2Quat(quat, np.asarray(axis, dtype=np.float64), float(angle))
    return _pose(np.zeros(3), quat)


def _inv(T: np.ndarray) -> np.ndarray:
    Ti = np.eye(4)
    Ti[:3, :3] = T[:3, :3].T
    Ti[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return Ti


def _rpy_to_mat(rpy) -> np.ndarray:
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    # URDF: fixed-axis roll about x, then pitch about y, then yaw about z: R = Rz Ry Rx
    return np.array([
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ])


def mat_to_rpy(R: np.ndarray) -> tuple[float, float, float]:
    """URDF roll-pitch-yaw of a rotation matrix, accurate near pitch = +-pi/2 too."""
    cp = math.hypot(R[0, 0], R[1, 0])
    pitch = math.atan2(-R[2, 0], cp)
    if cp > 1e-9:
        roll = math.atan2(R[2, 1], R[2, 2])
        yaw = math.atan2(R[1, 0], R[0, 0])
    else:  # gimbal lock: only roll -/+ yaw is defined; put it all in roll
        roll = math.atan2(-R[1, 2], R[1, 1])
        yaw = 0.0
    rpy = (roll, pitch, yaw)
    # cheap guard: the URDF must reproduce MuJoCo's rotation to float64 precision
    assert np.abs(_rpy_to_mat(rpy) - R).max() < 1e-9, "rpy round trip failed"
    return rpy


# ----------------------------------------------------------------------------- xml


def _num(x: float) -> str:
    x = float(x)
    # |x| < 1e-14 is round-off of the frame algebra (1e-14 m, 1e-14 rad): write a clean 0.
    # repr: the shortest string that round-trips a float64.
    return "0" if abs(x) < 1e-14 else repr(x)


def _vec(v: Iterable[float]) -> str:
    return " ".join(_num(x) for x in v)


def _origin(T: np.ndarray) -> str:
    return f'<origin xyz="{_vec(T[:3, 3])}" rpy="{_vec(mat_to_rpy(T[:3, :3]))}"/>'


def _is_identity(T: np.ndarray, tol: float = 1e-12) -> bool:
    return bool(np.abs(T - np.eye(4)).max() < tol)


# ----------------------------------------------------------------------------- model queries


def _name(model: mujoco.MjModel, obj: mujoco.mjtObj, i: int) -> str:
    return mujoco.mj_id2name(model, obj, i) or ""


def mesh_file(model: mujoco.MjModel, mesh_id: int) -> str:
    """The file name a mesh asset was loaded from, as written in the MJCF ('' if none)."""
    adr = model.mesh_pathadr[mesh_id]
    if adr < 0:
        return ""
    end = model.paths.find(b"\0", adr)
    return model.paths[adr:end].decode()


def mesh_transform(model: mujoco.MjModel, mesh_id: int) -> np.ndarray:
    """T_mesh: compiled (re-centred) mesh frame -> original file frame (after scaling).

    ``scale * v_file = T_mesh @ v_compiled``.
    """
    return _pose(model.mesh_pos[mesh_id], model.mesh_quat[mesh_id])


def geom_rgba(model: mujoco.MjModel, geom_id: int) -> np.ndarray:
    """The colour MuJoCo renders a geom with (textures ignored)."""
    rgba = np.asarray(model.geom_rgba[geom_id], dtype=np.float32)
    mat = model.geom_matid[geom_id]
    if mat >= 0 and np.allclose(rgba, _DEFAULT_RGBA):
        rgba = np.asarray(model.mat_rgba[mat], dtype=np.float32)
    return rgba


def subtree_bodies(model: mujoco.MjModel, root_bodies: Iterable[str]) -> list[int]:
    """Body ids of the chosen subtrees, parents before children."""
    roots = []
    for name in root_bodies:
        bid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, name)
        if bid < 0:
            raise InputError(f"MuJoCo model has no body {name!r} (root bodies to export)")
        if bid == 0:
            raise InputError("the world body cannot be an exported root; name the robot's base bodies")
        roots.append(bid)
    chosen = set()
    for b in range(1, model.nbody):  # MuJoCo orders bodies depth-first, parents first
        if b in roots or model.body_parentid[b] in chosen:
            chosen.add(b)
    return sorted(chosen)


# ----------------------------------------------------------------------------- export


def export_urdf(
    model: mujoco.MjModel,
    root_bodies: Iterable[str],
    *,
    mesh_dir: str | os.PathLike | None = None,
    mimic: MimicSpec | None = None,
    robot_name: str = "robot",
    mesh_uri: Callable[[Path], str] | None = None,
) -> str:
    """URDF text of the subtrees rooted at ``root_bodies`` (everything else excluded).

    ``mesh_dir`` resolves relative mesh file names of the MJCF (the directory of
    the main MJCF file, or its ``meshdir``). ``mesh_uri`` turns an existing mesh
    file's absolute path into the URDF ``filename`` (default: the absolute path;
    use it to write ``package://`` URIs). ``mimic`` maps follower joint ->
    ``(leader, multiplier, offset)``: follower = offset + multiplier * leader.
    """
    root_bodies = list(root_bodies)
    bodies = subtree_bodies(model, root_bodies)
    body_set = set(bodies)
    mesh_uri = mesh_uri or (lambda p: str(p))

    # Root bodies hang off bodies that are not exported; their frames must be
    # static, which holds iff no ancestor has a joint. Their world pose is then
    # the one mj_kinematics computes at any configuration.
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    for b in bodies:
        if model.body_parentid[b] in body_set:
            continue
        a = model.body_parentid[b]
        while a != 0:
            if model.body_jntnum[a]:
                raise InputError(
                    f"root body {_name(model, mujoco.mjtObj.mjOBJ_BODY, b)!r} moves with joints of its "
                    f"ancestor {_name(model, mujoco.mjtObj.mjOBJ_BODY, a)!r}; export from a fixed base")
            a = model.body_parentid[a]

    links: list[str] = [f'  <link name="{WORLD_LINK}"/>']
    joints: list[str] = []
    joint_names: set[str] = set()
    exported_moving: set[str] = set()

    def add_joint(name, jtype, parent, child, T_origin, axis=None, limit=None):
        if name in joint_names:
            raise InputError(f"duplicate URDF joint name {name!r} while exporting the MuJoCo model")
        joint_names.add(name)
        lines = [f"  <joint name={quoteattr(name)} type=\"{jtype}\">",
                 f"    <parent link={quoteattr(parent)}/>",
                 f"    <child link={quoteattr(child)}/>",
                 f"    {_origin(T_origin)}"]
        if axis is not None:
            lines.append(f'    <axis xyz="{_vec(axis)}"/>')
        if limit is not None:
            # effort/velocity are required by the URDF schema; MJCF has no
            # equivalent worth carrying, so they are placeholders.
            lines.append(f'    <limit lower="{_num(limit[0])}" upper="{_num(limit[1])}" effort="0" velocity="0"/>')
        if name in (mimic or {}):
            leader, mult, off = mimic[name]
            lines.append(f'    <mimic joint={quoteattr(leader)} multiplier="{_num(mult)}" offset="{_num(off)}"/>')
        lines.append("  </joint>")
        joints.append("\n".join(lines))

    for b in bodies:
        body = _name(model, mujoco.mjtObj.mjOBJ_BODY, b)
        if not body:
            raise InputError(f"MuJoCo body {b} has no name; name every body of the exported robot")
        parent_id = model.body_parentid[b]
        if parent_id in body_set:
            parent = _name(model, mujoco.mjtObj.mjOBJ_BODY, parent_id)
            T_parent = np.eye(4)
        else:  # a root: static parent frame expressed in the world
            parent = WORLD_LINK
            T_parent = _pose(data.xpos[parent_id], data.xquat[parent_id])
        # Transform accumulated since the last URDF joint frame (starts at the body offset).
        T_pending = T_parent @ _pose(model.body_pos[b], model.body_quat[b])
        jnt_ids = range(model.body_jntadr[b], model.body_jntadr[b] + model.body_jntnum[b])
        for k, j in enumerate(jnt_ids):
            jname = _name(model, mujoco.mjtObj.mjOBJ_JOINT, j)
            jtype = model.jnt_type[j]
            if jtype not in (mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE):
                raise InputError(
                    f"joint {jname or j!r} of body {body!r} is a ball or free joint; URDF cannot express it")
            if not jname:
                raise InputError(f"an unnamed joint on body {body!r}; name every exported joint")
            axis = np.asarray(model.jnt_axis[j], dtype=np.float64)
            anchor = np.asarray(model.jnt_pos[j], dtype=np.float64)
            ref = float(model.qpos0[model.jnt_qposadr[j]])
            # MuJoCo: frame <- frame * Tr(anchor) * Motion(axis, q - ref) * Tr(-anchor)
            T_origin = T_pending @ _translation(anchor)
            if jtype == mujoco.mjtJoint.mjJNT_HINGE:
                T_pending = _axis_angle(axis, -ref) @ _translation(-anchor)
                urdf_type = "revolute" if model.jnt_limited[j] else "continuous"
                limit = tuple(model.jnt_range[j]) if model.jnt_limited[j] else None
            else:
                T_pending = _translation(-ref * axis) @ _translation(-anchor)
                urdf_type = "prismatic"
                # URDF requires limits on prismatic joints; an unlimited slide gets a wide range
                limit = tuple(model.jnt_range[j]) if model.jnt_limited[j] else (-1e3, 1e3)
            last = k == len(jnt_ids) - 1
            child = body if (last and _is_identity(T_pending)) else f"{body}__{jname}"
            if child != body:
                links.append(f"  <link name={quoteattr(child)}/>")
            add_joint(jname, urdf_type, parent, child, T_origin, axis=axis, limit=limit)
            exported_moving.add(jname)
            parent = child
        if parent != body:  # no joints, or a transform left after the last joint
            add_joint(f"{body}__fixed", "fixed", parent, body, T_pending)
        links.append(_link_xml(model, b, body, mesh_dir, mesh_uri))

    for follower, spec in (mimic or {}).items():
        if follower not in exported_moving or spec[0] not in exported_moving:
            raise InputError(
                f"mimic {follower!r} <- {spec[0]!r}: both must be hinge/slide joints of the exported bodies")

    header = ("<?xml version=\"1.0\"?>\n"
              "<!-- Generated by imac_data.core.robot.mjcf from a compiled MuJoCo model; "
              "link frames are MuJoCo body frames. -->\n")
    return header + f"<robot name={quoteattr(robot_name)}>\n" + "\n".join(links + joints) + "\n</robot>\n"


def _link_xml(model, b: int, body: str, mesh_dir, mesh_uri) -> str:
    visuals = []
    for g in range(model.body_geomadr[b], model.body_geomadr[b] + model.body_geomnum[b]):
        rgba = geom_rgba(model, g)
        if model.geom_group[g] not in VISIBLE_GROUPS or rgba[3] <= 0:
            continue  # MuJoCo does not draw it by default, so neither do we
        gname = _name(model, mujoco.mjtObj.mjOBJ_GEOM, g) or f"{body}/geom{g}"
        T_geom = _pose(model.geom_pos[g], model.geom_quat[g])
        size = model.geom_size[g]
        gtype = model.geom_type[g]
        if gtype == mujoco.mjtGeom.mjGEOM_MESH:
            m = model.geom_dataid[g]
            path = _resolve_mesh(model, m, mesh_dir)
            T_geom = T_geom @ _inv(mesh_transform(model, m))  # undo MuJoCo's re-centring
            geometry = f'<mesh filename={quoteattr(mesh_uri(path))} scale="{_vec(model.mesh_scale[m])}"/>'
        elif gtype == mujoco.mjtGeom.mjGEOM_BOX:
            geometry = f'<box size="{_vec(2 * size)}"/>'  # MuJoCo: half sizes
        elif gtype == mujoco.mjtGeom.mjGEOM_SPHERE:
            geometry = f'<sphere radius="{_num(size[0])}"/>'
        elif gtype == mujoco.mjtGeom.mjGEOM_CYLINDER:
            geometry = f'<cylinder radius="{_num(size[0])}" length="{_num(2 * size[1])}"/>'
        else:
            raise InputError(
                f"geom {gname!r} of body {body!r} has type {mujoco.mjtGeom(gtype).name}, which the URDF "
                f"export does not support (box, sphere, cylinder, mesh); put it in group >= 3 or replace it")
        visuals.append(
            f"    <visual name={quoteattr(gname)}>\n"
            f"      {_origin(T_geom)}\n"
            f"      <geometry>{geometry}</geometry>\n"
            f"      <material name={quoteattr(gname + '/material')}><color rgba=\"{_vec(rgba)}\"/></material>\n"
            f"    </visual>")
    if not visuals:
        return f"  <link name={quoteattr(body)}/>"
    return f"  <link name={quoteattr(body)}>\n" + "\n".join(visuals) + "\n  </link>"


def _resolve_mesh(model, mesh_id: int, mesh_dir) -> Path:
    name = _name(model, mujoco.mjtObj.mjOBJ_MESH, mesh_id)
    fname = mesh_file(model, mesh_id)
    if not fname:
        raise InputError(f"mesh {name!r} has no file (inline vertices?); the URDF export needs mesh files")
    path = Path(fname)
    if not path.is_absolute():
        if mesh_dir is None:
            raise InputError(f"mesh {name!r} has the relative file {fname!r}; pass mesh_dir to resolve it")
        path = Path(mesh_dir) / path
    path = path.resolve()
    if not path.is_file():
        raise InputError(f"mesh file {path} of mesh {name!r} does not exist")
    return path


def write_text_atomic(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` to ``path`` via a temporary file + rename, so readers never see half a file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def write_urdf(path: str | os.PathLike, model: mujoco.MjModel, root_bodies: Iterable[str], **kwargs) -> Path:
    """:func:`export_urdf` written atomically to ``path``."""
    return write_text_atomic(path, export_urdf(model, root_bodies, **kwargs))
