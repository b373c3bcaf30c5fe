"""What a URDF offers a recipe: its movable joints, limits, mimic relations and visual links.

Writing a recipe's ``robot:`` block for a new robot starts from the URDF's joint names.
:func:`summarize_urdf` reads them the way :class:`~imac_data.core.robot.model.RobotModel` will (the
spec's default axis, a floating root held fixed, unsupported joint types refused) and
checks that every visual mesh resolves; :func:`recipe_block` turns that into a ``robot:``
block to edit::

    imac robot joints ROBOT.urdf [--package-dir NAME=PATH ...]

The block lists every movable, non-mimic joint in URDF order, one ``joint_map`` entry per
joint; the user reorders it to the dataset's ``observation.state`` / ``action`` order and
deletes what the dataset does not record. ``gripper_links`` is a guess (the links moved
by the finger joints) and says so.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import yourdfpy

from imac_data.core.robot.model import MOVABLE_JOINT_TYPES, kinematic_urdf, resolve_filename
from imac_data.errors import InputError

__all__ = ["JointInfo", "VisualLinkInfo", "UrdfSummary", "summarize_urdf", "recipe_block", "format_summary", "guess_gripper_links"]

# How a recipe entry converts a dataset value in other units to a joint position.
AFFINE_HINT = ("# An entry whose dataset values are not radians / metres (degrees, -100..100, a 0..1 gripper)\n"
               "# needs an affine map, position = offset + scale * value: {joint: JOINT, scale: S, offset: O}.")


@dataclass(frozen=True)
class JointInfo:
    name: str
    type: str  # revolute | continuous | prismatic
    parent: str
    child: str
    axis: tuple[float, float, float]  # in the joint frame; the spec's (1, 0, 0) when absent
    lower: float | None  # radians or metres; None = unlimited (continuous) or not given
    upper: float | None
    mimic: tuple[str, float, float] | None  # (leader, multiplier, offset): follows its leader

    @property
    def unit(self) -> str:
        return "m" if self.type == "prismatic" else "rad"


@dataclass(frozen=True)
class VisualLinkInfo:
    link: str
    visuals: int
    meshes: tuple[str, ...]  # mesh filenames as written in the URDF
    missing: tuple[str, ...]  # what does not resolve to a file, and why


@dataclass(frozen=True)
class UrdfSummary:
    path: Path
    name: str
    root: str
    joints: tuple[JointInfo, ...]  # movable joints, URDF order
    held_fixed: tuple[str, ...]  # floating root joints, held at their origin
    visual_links: tuple[VisualLinkInfo, ...]
    package_dirs: tuple[tuple[str, Path], ...]

    @property
    def drivable(self) -> tuple[JointInfo, ...]:
        """The joints a dataset vector can drive (mimic followers follow their leaders)."""
        return tuple(j for j in self.joints if j.mimic is None)

    def followers(self, leader: str) -> list[str]:
        return [j.name for j in self.joints if j.mimic is not None and j.mimic[0] == leader]


def _limit(joint: yourdfpy.Joint) -> tuple[float | None, float | None]:
    if joint.type == "continuous" or joint.limit is None:
        return None, None
    return joint.limit.lower, joint.limit.upper


def summarize_urdf(path: str | Path, package_dirs: Mapping[str, str | Path] | None = None) -> UrdfSummary:
    """Parse a URDF as the robot model will; :class:`InputError` on what it would refuse."""
    path = Path(path)
    package_dirs = {k: Path(v) for k, v in (package_dirs or {}).items()}
    if not path.is_file():
        raise InputError(f"URDF file {path} does not exist")
    try:
        urdf = yourdfpy.URDF.load(str(path), build_scene_graph=False, load_meshes=False)
    except Exception as e:  # yourdfpy raises assorted errors on malformed XML
        raise InputError(f"cannot parse URDF {path}: {e}") from e
    _, held_fixed = kinematic_urdf(path.read_text(), path)  # type checks, as RobotModel does them

    joints = []
    for j in urdf.robot.joints:
        if j.type not in MOVABLE_JOINT_TYPES:
            continue
        mimic = None
        if j.mimic is not None:
            mimic = (j.mimic.joint, 1.0 if j.mimic.multiplier is None else float(j.mimic.multiplier),
                     0.0 if j.mimic.offset is None else float(j.mimic.offset))
        axis = (1.0, 0.0, 0.0) if j.axis is None else tuple(float(v) for v in j.axis)
        joints.append(JointInfo(j.name, j.type, j.parent, j.child, axis, *_limit(j), mimic))

    visual_links = []
    for link in urdf.robot.links:
        if not link.visuals:
            continue
        meshes, missing = [], []
        for v in link.visuals:
            if v.geometry is None or v.geometry.mesh is None:
                continue
            fname = v.geometry.mesh.filename
            meshes.append(fname)
            try:
                resolved = resolve_filename(fname, path, package_dirs)
            except InputError:
                pkg = fname[len("package://"):].partition("/")[0]
                missing.append(f"{fname} (package {pkg!r}: give --package-dir {pkg}=PATH)")
                continue
            if not resolved.is_file():
                missing.append(f"{fname} (no file {resolved})")
        visual_links.append(VisualLinkInfo(link.name, len(link.visuals), tuple(meshes), tuple(missing)))

    children = {j.child for j in urdf.robot.joints}
    roots = [link.name for link in urdf.robot.links if link.name not in children]
    return UrdfSummary(path=path, name=urdf.robot.name or path.stem, root=", ".join(roots), joints=tuple(joints),
                       held_fixed=held_fixed, visual_links=tuple(visual_links),
                       package_dirs=tuple(package_dirs.items()))


def guess_gripper_links(summary: UrdfSummary, urdf: yourdfpy.URDF | None = None) -> list[str]:
    """Links moved by finger joints: prismatic or mimic-related joints with no other movable
    joint below them, and every link below those joints that has visual geometry."""
    below: dict[str, list[str]] = {}  # link -> child links
    joint_of_child: dict[str, str] = {}
    if urdf is None:
        urdf = yourdfpy.URDF.load(str(summary.path), build_scene_graph=False, load_meshes=False)
    for j in urdf.robot.joints:
        below.setdefault(j.parent, []).append(j.child)
        joint_of_child[j.child] = j.name
    movable = {j.name: j for j in summary.joints}
    leaders = {j.mimic[0] for j in summary.joints if j.mimic is not None}

    def subtree(link: str) -> list[str]:
        out = [link]
        for child in below.get(link, []):
            out += subtree(child)
        return out

    visual = {v.link for v in summary.visual_links}
    links: list[str] = []
    for j in summary.joints:
        finger = j.type == "prismatic" or j.mimic is not None or j.name in leaders
        sub = subtree(j.child)
        if not finger or any(joint_of_child.get(link) in movable for link in sub[1:]):
            continue
        links += [link for link in sub if link in visual and link not in links]
    return links


def _fmt(x: float | None) -> str:
    return "-" if x is None else f"{x:.6g}"


def format_summary(summary: UrdfSummary) -> str:
    lines = [f"URDF {summary.path}: robot {summary.name!r}, root link {summary.root}", "",
             f"movable joints ({len(summary.joints)}, URDF order):"]
    width = max((len(j.name) for j in summary.joints), default=4)
    lines.append(f"  {'name':<{width}}  {'type':<10}  {'lower':>9}  {'upper':>9}  unit  axis        parent -> child")
    for j in summary.joints:
        axis = " ".join(f"{v:g}" for v in j.axis)
        line = (f"  {j.name:<{width}}  {j.type:<10}  {_fmt(j.lower):>9}  {_fmt(j.upper):>9}  {j.unit:<4}  "
                f"{axis:<10}  {j.parent} -> {j.child}")
        if j.mimic is not None:
            lead, mult, off = j.mimic
            line += f"   mimic: = {off:g} + {mult:g} * {lead}"
        lines.append(line)
    if summary.held_fixed:
        lines += ["", f"floating root joint(s) held fixed at their origin: {', '.join(summary.held_fixed)}"]
    lines += ["", f"links with visuals ({len(summary.visual_links)}):"]
    for v in summary.visual_links:
        meshes = ", ".join(v.meshes) if v.meshes else "primitives"
        lines.append(f"  {v.link}: {v.visuals} visual(s): {meshes}")
        lines += [f"    MISSING {m}" for m in v.missing]
    return "\n".join(lines)


def recipe_block(summary: UrdfSummary, gripper_links: Sequence[str] = ()) -> str:
    """A recipe ``robot:`` block to start from (YAML, with comments saying what to edit)."""
    out = [f"# Recipe `robot:` block for {summary.name!r}, to start from (imac robot joints).",
           "robot:",
           f"  urdf: {summary.path.resolve()}"]
    if summary.package_dirs:
        out.append("  package_dirs:")
        out += [f"    {name}: {Path(d).resolve()}" for name, d in summary.package_dirs]
    out += ["  # One entry per index of the dataset's observation.state / action vector, in that order:",
            "  # reorder, and delete the joints the dataset does not record (they stay at 0).",
            *("  " + line for line in AFFINE_HINT.splitlines()),
            "  joint_map:"]
    width = max((len(j.name) for j in summary.drivable), default=0)
    for j in summary.drivable:
        rng = "unlimited" if j.lower is None and j.upper is None else f"[{_fmt(j.lower)}, {_fmt(j.upper)}]"
        note = f"{j.type} {rng} {j.unit}"
        followers = summary.followers(j.name)
        if followers:
            note += f"; moves {', '.join(followers)} (mimic)"
        out.append(f"    - {j.name:<{width}}  # {note}")
    if not summary.drivable:
        out.append("    []  # the URDF has no movable joint")
    guess = ", ".join(gripper_links)
    out.append(f"  gripper_links: [{guess}]  # guessed: the links moved by the finger joints; check")
    return "\n".join(out) + "\n"
