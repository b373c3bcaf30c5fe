"""Robot description: dataset joint vector -> URDF joints -> link poses and visual meshes.

A :class:`RobotConfig` says which URDF to use and how each index of the
dataset's ``observation.state`` / ``action`` vector maps to a URDF joint
(docs/dataset-format.md, "Conventions"): each index names a URDF joint, through an explicit affine
map where the recorded unit is not the URDF's (:class:`JointEntry`: a gripper's
normalised opening to a finger slide, degrees to radians, ...), and URDF
``<mimic>`` joints (the second finger) follow their leader.

:class:`RobotModel` loads the URDF once (yourdfpy for the visual geometry,
pytorch-kinematics for FK) and then works on torch tensors of any batch shape
``(*B, D)``, on CPU or CUDA, in float32 or float64. World = the URDF root frame.

URDFs are read as the spec says where pytorch-kinematics does not (:func:`kinematic_urdf`):
a movable joint without ``<axis>`` turns about x; a ``floating`` joint off the root link is
held fixed at its origin; ``planar`` joints and other floating joints are refused by name.
A material defined inside one link's visual may be referred to by name from any other.
``imac robot joints ROBOT.urdf`` lists what a recipe needs
(:mod:`imac_data.core.robot.urdf_summary`).
"""

from __future__ import annotations

import hashlib
import math
import xml.etree.ElementTree as ET
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from imac_data.errors import InputError

if TYPE_CHECKING:  # imported where used: together 1.5 s, and a process that reads a dataset never needs them
    import pytorch_kinematics as pk
    import trimesh
    import yourdfpy

_DEFAULT_RGBA = (0.5, 0.5, 0.5, 1.0)  # MuJoCo's default geom colour, for visuals without a material


# ----------------------------------------------------------------------------- config


@dataclass(frozen=True)
class JointEntry:
    """One entry of the dataset joint vector -> its URDF joint: ``q_urdf = offset + scale * value``.

    Any entry may carry an affine map: a gripper's normalised opening to a finger slide in
    metres, a joint recorded in degrees (``scale = pi / 180``), a -100..100 range, ...
    """

    index: int  # index in the dataset joint vector
    joint: str  # URDF joint it drives
    scale: float = 1.0
    offset: float = 0.0

    def __post_init__(self):
        if not (math.isfinite(self.scale) and math.isfinite(self.offset)) or self.scale == 0:
            raise InputError(f"joint map of index {self.index} ({self.joint!r}): scale must be finite and "
                             f"non-zero and offset finite, got scale={self.scale}, offset={self.offset}")

    @property
    def is_identity(self) -> bool:
        return self.scale == 1.0 and self.offset == 0.0

    def to_dict(self) -> str | dict:
        """The recipe / ``info.json`` form: the joint name, or ``{joint, scale, offset}``."""
        if self.is_identity:
            return self.joint
        return {"joint": self.joint, "scale": self.scale, "offset": self.offset}


# The name of the affine entry when only grippers could carry one (kept for callers).
GripperMap = JointEntry


@dataclass(frozen=True)
class RobotConfig:
    """Which URDF, and how the dataset's joint vector drives it.

    ``joint_map[i]`` is the URDF joint name of dataset index ``i`` (identity map), or a
    :class:`JointEntry` (whose ``index`` must be ``i``) with its affine map. URDF joints
    that are neither mapped nor mimic followers stay at 0. ``package_dirs`` maps a
    package name to the directory that ``package://<name>/`` stands for.
    """

    name: str
    urdf_path: Path
    joint_map: tuple[str | JointEntry, ...]
    gripper_links: tuple[str, ...] = ()
    package_dirs: tuple[tuple[str, Path], ...] = ()

    def __post_init__(self):
        # Normalise containers so configs are hashable and comparable (frozen dataclass).
        pkg = self.package_dirs.items() if isinstance(self.package_dirs, Mapping) else self.package_dirs
        object.__setattr__(self, "urdf_path", Path(self.urdf_path))
        object.__setattr__(self, "joint_map", tuple(self.joint_map))
        object.__setattr__(self, "gripper_links", tuple(self.gripper_links))
        object.__setattr__(self, "package_dirs", tuple((str(k), Path(v)) for k, v in pkg))
        if not self.name:
            raise InputError("robot config needs a name")
        if not self.joint_map:
            raise InputError(f"robot {self.name!r}: joint_map is empty")
        seen = set()
        for i, entry in enumerate(self.joint_map):
            if isinstance(entry, JointEntry):
                if entry.index != i:
                    raise InputError(f"robot {self.name!r}: joint_map[{i}] is a JointEntry with index "
                                     f"{entry.index}")
                joint = entry.joint
            elif isinstance(entry, str) and entry:
                joint = entry
            else:
                raise InputError(f"robot {self.name!r}: joint_map[{i}] must be a joint name or a JointEntry, "
                                 f"got {entry!r}")
            if joint in seen:
                raise InputError(f"robot {self.name!r}: joint {joint!r} is mapped twice in joint_map")
            seen.add(joint)

    @property
    def dof(self) -> int:
        return len(self.joint_map)

    def joint_name(self, i: int) -> str:
        entry = self.joint_map[i]
        return entry.joint if isinstance(entry, JointEntry) else entry

    def joint_entry(self, i: int) -> JointEntry:
        """Entry ``i`` with its affine map (identity for a plain joint name)."""
        entry = self.joint_map[i]
        return entry if isinstance(entry, JointEntry) else JointEntry(i, entry)

    def joint_map_dict(self) -> list:
        """The joint map as recorded in recipes and ``info.json``: a joint name per identity
        entry, ``{joint, scale, offset}`` per affine one."""
        return [self.joint_entry(i).to_dict() for i in range(self.dof)]

    @staticmethod
    def parse_joint_map(entries, where: str = "joint_map") -> tuple[str | JointEntry, ...]:
        """The inverse of :meth:`joint_map_dict` (also accepts the old gripper form
        ``{gripper: joint, scale, offset}``); :class:`InputError` names the entry."""
        if not isinstance(entries, (list, tuple)) or not entries:
            raise InputError(f"{where}: expected a non-empty list of joint names or {{joint, scale, offset}}")
        out: list[str | JointEntry] = []
        for i, e in enumerate(entries):
            if isinstance(e, JointEntry):
                out.append(e if e.index == i else JointEntry(i, e.joint, e.scale, e.offset))
                continue
            if isinstance(e, str) and e:
                out.append(e)
                continue
            if not isinstance(e, Mapping):
                raise InputError(f"{where}[{i}]: expected a joint name or {{joint, scale, offset}}, got {e!r}")
            e = dict(e)
            name_key = "joint" if "joint" in e else "gripper" if "gripper" in e else None
            unknown = sorted(set(e) - {name_key, "scale", "offset"})
            if name_key is None or unknown or ("joint" in e and "gripper" in e):
                raise InputError(f"{where}[{i}]: expected {{joint: NAME, scale: S, offset: O}}, got {e!r}")
            try:
                scale, offset = float(e.get("scale", 1.0)), float(e.get("offset", 0.0))
            except (TypeError, ValueError):
                raise InputError(f"{where}[{i}]: scale and offset must be numbers, got {e!r}") from None
            try:
                entry = JointEntry(i, str(e[name_key]), scale, offset)
            except InputError as err:
                raise InputError(f"{where}[{i}]: {err}") from None
            out.append(entry.joint if entry.is_identity else entry)
        return tuple(out)

    def validate(self, urdf: yourdfpy.URDF) -> None:
        """Check the config against a parsed URDF; InputError names what is missing."""
        movable = {j.name: j for j in urdf.robot.joints if j.type != "fixed"}
        for i in range(self.dof):
            joint = self.joint_name(i)
            if joint not in movable:
                what = "is fixed in" if joint in urdf.joint_map else "does not exist in"
                raise InputError(f"robot {self.name!r}: joint {joint!r} (dataset index {i}) {what} the URDF "
                                 f"{self.urdf_path}")
            if movable[joint].mimic is not None:
                raise InputError(f"robot {self.name!r}: joint {joint!r} (dataset index {i}) is a mimic joint in "
                                 f"{self.urdf_path}; map its leader {movable[joint].mimic.joint!r} instead")
        for link in self.gripper_links:
            if link not in urdf.link_map:
                raise InputError(f"robot {self.name!r}: gripper link {link!r} does not exist in the URDF "
                                 f"{self.urdf_path}")


# ----------------------------------------------------------------------------- meshes


@dataclass(frozen=True, eq=False)
class VisualMesh:
    """One URDF visual, in its link's frame (visual origin and scale applied)."""

    link: str
    vertices: np.ndarray  # (V, 3) float32, link frame
    faces: np.ndarray  # (F, 3) int32
    rgba: np.ndarray  # (4,) float32 in [0, 1]
    name: str = ""  # the URDF visual name (our MJCF export: the MuJoCo geom name)


def resolve_filename(fname: str, urdf_path: Path, package_dirs: Mapping[str, Path]) -> Path:
    """A URDF mesh ``filename`` -> local path (``package://``, ``file://``, absolute, or URDF-relative)."""
    if fname.startswith("package://"):
        pkg, _, rel = fname[len("package://"):].partition("/")
        if pkg not in package_dirs:
            raise InputError(f"mesh {fname!r} in {urdf_path} uses package {pkg!r}, which is not in the robot "
                             f"config's package_dirs ({sorted(package_dirs)})")
        return Path(package_dirs[pkg]) / rel
    if fname.startswith("file://"):
        fname = fname[len("file://"):]
    path = Path(fname)
    return path if path.is_absolute() else urdf_path.parent / path


def _material_rgba(visual: yourdfpy.Visual, materials: Mapping[str, yourdfpy.Material]) -> np.ndarray:
    mat = visual.material
    if mat is not None and mat.color is None and mat.name in materials:
        mat = materials[mat.name]  # a reference by name to a material defined elsewhere
    rgba = mat.color.rgba if (mat is not None and mat.color is not None) else _DEFAULT_RGBA
    return np.asarray(rgba, dtype=np.float32)


def named_materials(urdf: yourdfpy.URDF) -> dict[str, yourdfpy.Material]:
    """Every named material with a colour: the robot-level ones, then those defined inside a
    link's visual (urdfdom makes those global too, so another link may refer to them by
    name; exported Panda and UR URDFs do). The first definition of a name wins, as in urdfdom."""
    out: dict[str, yourdfpy.Material] = {}
    inline = (v.material for link in urdf.robot.links for v in link.visuals)
    for mat in (*urdf.robot.materials, *inline):
        if mat is not None and mat.name and mat.color is not None:
            out.setdefault(mat.name, mat)
    return out


def _file_unit(mesh: trimesh.Trimesh, path: Path) -> float:
    """Metres per unit of a mesh file that declares its unit (Collada's ``<unit meter=...>``,
    which CAD exporters set to millimetres or centimetres; RViz and Gazebo apply it); 1 for
    formats without one (STL, OBJ, PLY)."""
    import trimesh  # heavy: only where a mesh is loaded

    units = getattr(mesh, "units", None)
    if not units:
        return 1.0
    try:
        return float(trimesh.units.unit_conversion(units, "meters"))
    except (ValueError, KeyError) as e:
        raise InputError(f"mesh file {path} declares the unit {units!r}, which is not a length unit") from e


def _geometry_mesh(geom: yourdfpy.Geometry, visual_name: str, urdf_path: Path,
                   package_dirs: Mapping[str, Path]) -> trimesh.Trimesh:
    import trimesh  # heavy: only where a mesh is made

    if geom.mesh is not None:
        path = resolve_filename(geom.mesh.filename, urdf_path, package_dirs)
        if not path.is_file():
            raise InputError(f"mesh file {path} (filename {geom.mesh.filename!r} of visual {visual_name!r}) "
                             f"referenced by the URDF {urdf_path} does not exist")
        # process=True merges duplicate STL vertices (as MuJoCo does); force="mesh" flattens scenes.
        mesh = trimesh.load(str(path), force="mesh")
        if len(getattr(mesh, "faces", ())) == 0:  # a point cloud, or an empty scene
            raise InputError(f"mesh file {path} (visual {visual_name!r} in {urdf_path}) has no faces")
        scale = 1.0 if geom.mesh.scale is None else np.broadcast_to(np.asarray(geom.mesh.scale, float), 3)
        return trimesh.Trimesh(mesh.vertices * (scale * _file_unit(mesh, path)), mesh.faces, process=False)
    if geom.box is not None:
        return trimesh.creation.box(extents=geom.box.size)
    if geom.sphere is not None:
        return trimesh.creation.icosphere(subdivisions=3, radius=geom.sphere.radius)
    if geom.cylinder is not None:
        return trimesh.creation.cylinder(radius=geom.cylinder.radius, height=geom.cylinder.length, sections=32)
    raise InputError(f"visual {visual_name!r} in {urdf_path} has no geometry")


def load_visual_meshes(urdf: yourdfpy.URDF, urdf_path: Path,
                       package_dirs: Mapping[str, Path]) -> list[VisualMesh]:
    materials = named_materials(urdf)
    out = []
    for link in urdf.robot.links:
        for k, visual in enumerate(link.visuals):
            name = visual.name or f"{link.name}/visual{k}"
            mesh = _geometry_mesh(visual.geometry, name, urdf_path, package_dirs)
            origin = np.eye(4) if visual.origin is None else np.asarray(visual.origin, dtype=np.float64)
            vertices = mesh.vertices @ origin[:3, :3].T + origin[:3, 3]
            out.append(VisualMesh(link=link.name, vertices=np.array(vertices, dtype=np.float32),
                                  faces=np.asarray(mesh.faces, dtype=np.int32),
                                  rgba=_material_rgba(visual, materials), name=name))
    return out


# ----------------------------------------------------------------------------- model


class RobotModel:
    """FK and visual geometry of a robot, driven by the dataset joint vector."""

    def __init__(self, config: RobotConfig):
        self.config = config
        path = config.urdf_path
        if not path.is_file():
            raise InputError(f"robot {config.name!r}: URDF file {path} does not exist")
        self.urdf_text = path.read_text()
        self.urdf_hash = hashlib.sha256(self.urdf_text.encode()).hexdigest()
        import pytorch_kinematics as pk  # heavy (1 s with matplotlib): only where a robot is built
        import yourdfpy

        try:
            urdf = yourdfpy.URDF.load(str(path), build_scene_graph=False, load_meshes=False)
        except Exception as e:  # yourdfpy raises assorted errors on malformed XML
            raise InputError(f"robot {config.name!r}: cannot parse URDF {path}: {e}") from e
        self._kinematic_urdf, self.held_fixed = kinematic_urdf(self.urdf_text, path)
        for i in range(config.dof):
            if config.joint_name(i) in self.held_fixed:
                raise InputError(f"robot {config.name!r}: joint {config.joint_name(i)!r} (dataset index {i}) is "
                                 f"the floating root joint of {path}, held fixed at its origin; it cannot be "
                                 f"driven by the joint vector")
        config.validate(urdf)
        # URDF limits of the joints the dataset vector drives (imac_data.core.robot.joint_ranges): name -> (type, lower, upper)
        self.joint_limits: dict[str, tuple[str, float, float]] = {
            j.name: (j.type, float(j.limit.lower), float(j.limit.upper)) for j in urdf.robot.joints
            if j.type in ("revolute", "prismatic") and j.limit is not None and j.limit.lower is not None
            and j.limit.upper is not None and j.limit.lower < j.limit.upper}
        self.visual_meshes = load_visual_meshes(urdf, path, dict(config.package_dirs))

        # pytorch-kinematics ignores <mimic>: the chain treats followers as free
        # joints, so we compute every chain joint ourselves. Each chain joint is
        # an affine function of one dataset entry: q_chain[j] = a[j] * q[src[j]] + b[j]
        # (elementwise, not a matmul, so TF32 on GPUs cannot round it).
        chain = pk.build_chain_from_urdf(self._kinematic_urdf)
        self.joint_names: list[str] = chain.get_joint_parameter_names()
        self.link_names: list[str] = [chain.idx_to_frame[i] for i in range(len(chain.idx_to_frame))]
        self._chains = {(torch.float32, "cpu"): chain}
        self.mimic = _mimic_spec(urdf)  # follower -> (leader, multiplier, offset)
        src, a, b = _chain_joint_affine(self.joint_names, config, self.mimic)
        self._src = torch.tensor(src, dtype=torch.long)
        self._a = torch.tensor(a, dtype=torch.float64)
        self._b = torch.tensor(b, dtype=torch.float64)
        self._vertex_cache: dict = {}

    # ------------------------------------------------------------------ properties

    @property
    def name(self) -> str:
        return self.config.name

    @property
    def dof(self) -> int:
        """D, the length of the dataset joint vector."""
        return self.config.dof

    @property
    def gripper_links(self) -> tuple[str, ...]:
        return self.config.gripper_links

    def _chain(self, dtype: torch.dtype, device: torch.device) -> pk.Chain:
        key = (dtype, str(device))
        if key not in self._chains:
            import pytorch_kinematics as pk  # heavy: see __init__

            self._chains[key] = pk.build_chain_from_urdf(self._kinematic_urdf).to(dtype=dtype, device=device)
        return self._chains[key]

    # ------------------------------------------------------------------ joints

    def joint_positions(self, q) -> torch.Tensor:
        """Dataset joint vector ``(*B, D)`` -> chain joint values ``(*B, J)`` (order: ``joint_names``)."""
        q = _as_float_tensor(q)
        if q.ndim == 0 or q.shape[-1] != self.dof:
            raise InputError(f"robot {self.name!r}: joint vector must have {self.dof} entries in its last "
                             f"dimension, got shape {tuple(q.shape)}")
        bad = ~torch.isfinite(q)
        if bad.any():
            where = tuple(int(i) for i in torch.nonzero(bad)[0].tolist())
            i = where[-1]
            raise InputError(f"robot {self.name!r}: non-finite value {q[where].item()} at joint index {i} "
                             f"({self.config.joint_name(i)!r}), batch position {where[:-1]}")
        src = self._src.to(q.device)
        return q[..., src] * self._a.to(q) + self._b.to(q)

    def mapped_joints(self, q) -> np.ndarray:
        """Dataset joint vectors ``(*B, D)`` (the recorded units) -> ``(*B, D)`` float64: each entry through its
        joint-map entry, ``offset + scale * value``, the value of the URDF joint it drives (radians, metres). The
        robot's configuration whatever units the recording used: what distances between poses are measured in."""
        q = np.asarray(q, dtype=np.float64)
        if q.ndim == 0 or q.shape[-1] != self.dof:
            raise InputError(f"robot {self.name!r}: joint vector must have {self.dof} entries in its last "
                             f"dimension, got shape {q.shape}")
        entries = [self.config.joint_entry(i) for i in range(self.dof)]
        return np.array([e.offset for e in entries]) + np.array([e.scale for e in entries]) * q

    # ------------------------------------------------------------------ kinematics

    def _fk(self, th: torch.Tensor) -> dict[str, torch.Tensor]:
        batch = th.shape[:-1]
        chain = self._chain(th.dtype, th.device)
        T = chain.forward_kinematics_tensor(th.reshape(-1, th.shape[-1]))  # (L, N, 4, 4)
        return {name: T[i].reshape(*batch, 4, 4) for i, name in chain.idx_to_frame.items()}

    def link_poses(self, q) -> dict[str, torch.Tensor]:
        """World pose ``(*B, 4, 4)`` of every link for dataset joint vectors ``q`` ``(*B, D)``."""
        return self._fk(self.joint_positions(q))

    def forward_kinematics_joints(self, joint_values: Mapping[str, torch.Tensor | float]
                                  ) -> dict[str, torch.Tensor]:
        """Link poses from raw URDF joint values by name (each ``(*B,)``, broadcast together).

        Every non-mimic chain joint must be given; a mimic follower that is not
        given follows its leader, one that is given is used as is.
        """
        unknown = set(joint_values) - set(self.joint_names)
        if unknown:
            raise InputError(f"robot {self.name!r}: no movable joint(s) {sorted(unknown)} in "
                             f"{self.config.urdf_path}")
        missing = [n for n in self.joint_names if n not in joint_values and n not in self.mimic]
        if missing:
            raise InputError(f"robot {self.name!r}: missing values for joint(s) {missing}")
        tensors = {n: _as_float_tensor(v) for n, v in joint_values.items()}
        ref = next(iter(tensors.values()))
        dtype = ref.dtype
        for t in tensors.values():
            dtype = torch.promote_types(dtype, t.dtype)
        tensors = {n: t.to(device=ref.device, dtype=dtype) for n, t in tensors.items()}
        values: dict[str, torch.Tensor] = dict(tensors)

        def value(name: str) -> torch.Tensor:
            if name not in values:
                lead, mult, off = self.mimic[name]
                values[name] = off + mult * value(lead)
            return values[name]

        cols = torch.broadcast_tensors(*[value(n) for n in self.joint_names])
        th = torch.stack(cols, dim=-1)
        if not torch.isfinite(th).all():
            raise InputError(f"robot {self.name!r}: non-finite joint value(s) given")
        return self._fk(th)

    # ------------------------------------------------------------------ geometry

    def posed_vertices(self, q=None, *, link_poses: Mapping[str, torch.Tensor] | None = None
                       ) -> list[torch.Tensor]:
        """World vertices ``(*B, V, 3)`` of every visual mesh (same order as ``visual_meshes``)."""
        poses = self.link_poses(q) if link_poses is None else link_poses
        ref = next(iter(poses.values()))
        key = (ref.dtype, str(ref.device))
        if key not in self._vertex_cache:
            self._vertex_cache[key] = [torch.as_tensor(m.vertices).to(ref) for m in self.visual_meshes]
        out = []
        for mesh, v in zip(self.visual_meshes, self._vertex_cache[key]):
            T = poses[mesh.link]
            out.append(v @ T[..., :3, :3].transpose(-1, -2) + T[..., None, :3, 3])
        return out


def _mimic_spec(urdf: yourdfpy.URDF) -> dict[str, tuple[str, float, float]]:
    """URDF ``<mimic>`` tags as follower -> (leader, multiplier, offset), URDF defaults filled in."""
    return {j.name: (j.mimic.joint,
                     1.0 if j.mimic.multiplier is None else j.mimic.multiplier,
                     0.0 if j.mimic.offset is None else j.mimic.offset)
            for j in urdf.robot.joints if j.mimic is not None}


def _chain_joint_affine(joint_names: list[str], config: RobotConfig, mimic: Mapping[str, tuple[str, float, float]]
                        ) -> tuple[list[int], list[float], list[float]]:
    """For each chain joint j: (src[j], a[j], b[j]) with q_chain[j] = a[j] * q[src[j]] + b[j].

    Mapped joints apply their entry's affine map (identity for a plain name),
    mimic followers compose their leader's map with the mimic's; joints that
    nothing drives get a = b = 0 (held at 0).
    """
    direct = {}
    for i in range(config.dof):
        entry = config.joint_entry(i)
        direct[entry.joint] = (i, entry.scale, entry.offset)

    def resolve(name: str, seen: tuple[str, ...] = ()) -> tuple[int, float, float]:
        if name in direct:
            return direct[name]
        if name not in mimic:
            return (0, 0.0, 0.0)
        if name in seen:
            raise InputError(f"robot {config.name!r}: mimic joints form a cycle {seen + (name,)} in "
                             f"{config.urdf_path}")
        leader, mult, off = mimic[name]
        i, a, b = resolve(leader, seen + (name,))
        return i, mult * a, mult * b + off

    src, a, b = zip(*(resolve(n) for n in joint_names)) if joint_names else ((), (), ())
    return list(src), list(a), list(b)


# Joint types the kinematics supports; a `floating` joint off the root link is held fixed.
MOVABLE_JOINT_TYPES = ("revolute", "continuous", "prismatic")
_KINEMATIC_JOINT_CHILDREN = ("origin", "parent", "child", "axis", "limit")


def kinematic_urdf(urdf_text: str, urdf_path: Path | str = "<urdf>") -> tuple[str, tuple[str, ...]]:
    """The URDF as pytorch-kinematics should read it, and the floating joints held fixed.

    * Only the tree is kept (links without children, joints with origin/parent/child/axis/limit):
      pytorch-kinematics needs nothing else, and its bundled parser warns on valid attributes
      such as ``<visual name=...>`` and on common extensions such as ``<contact>``.
    * A movable joint without ``<axis>`` (or without its ``xyz``) gets the URDF spec's default
      ``1 0 0``; pytorch-kinematics would silently use z.
    * A ``floating`` joint whose parent is a root link (a mobile base, a robot placed in a
      world) is held fixed at its origin: the dataset vector cannot drive six free DoF.
    * ``planar`` joints, floating joints elsewhere and unknown types raise :class:`InputError`
      naming the file and joint (pytorch-kinematics would raise a bare ``KeyError``).
    """
    try:
        root = ET.fromstring(urdf_text.encode())
    except ET.ParseError as e:
        raise InputError(f"cannot parse URDF {urdf_path}: {e}") from e
    joints = root.findall("joint")  # direct children only: <transmission> also has <joint> tags
    children = {j.find("child").get("link") for j in joints if j.find("child") is not None}
    roots = {link.get("name") for link in root.findall("link")} - children
    held_fixed = []
    for joint in joints:
        name, kind = joint.get("name"), joint.get("type")
        parent = joint.find("parent")
        if kind == "floating" and parent is not None and parent.get("link") in roots:
            joint.set("type", "fixed")
            held_fixed.append(name)
        elif kind in ("floating", "planar"):
            where = "" if kind == "planar" else " that does not hang off the root link"
            raise InputError(f"URDF {urdf_path}: joint {name!r} is a {kind!r} joint{where}, which the robot "
                             f"model does not support (only {', '.join(MOVABLE_JOINT_TYPES)}, fixed, and a "
                             f"floating joint off the root link, held fixed); make it fixed, or split it into "
                             f"prismatic/revolute joints with dummy links")
        elif kind not in (*MOVABLE_JOINT_TYPES, "fixed"):
            raise InputError(f"URDF {urdf_path}: joint {name!r} has unknown type {kind!r}")
        if kind in MOVABLE_JOINT_TYPES:
            axis = joint.find("axis")
            if axis is None:
                axis = ET.SubElement(joint, "axis")
            xyz = axis.get("xyz", "1 0 0")  # the URDF spec's default axis
            try:
                norm = math.sqrt(sum(float(v) ** 2 for v in xyz.split()))
            except ValueError:
                norm = float("nan")
            if len(xyz.split()) != 3 or not norm > 0:
                raise InputError(f"URDF {urdf_path}: joint {name!r} has axis xyz={xyz!r}; it needs three "
                                 f"numbers, not all zero")
            axis.set("xyz", xyz)
        for child in list(joint):
            if child.tag not in _KINEMATIC_JOINT_CHILDREN:
                joint.remove(child)
    for child in list(root):
        if child.tag not in ("link", "joint"):
            root.remove(child)
    for link in root.findall("link"):
        for child in list(link):
            link.remove(child)
    return ET.tostring(root, encoding="unicode"), tuple(held_fixed)


def _as_float_tensor(x) -> torch.Tensor:
    t = torch.as_tensor(x)
    return t if t.is_floating_point() else t.to(torch.get_default_dtype())
