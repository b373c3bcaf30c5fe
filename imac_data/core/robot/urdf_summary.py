"""What a URDF offers a recipe: its movable joints, limits, mimic relations and visual links.

Writing a recipe's ``robot:`` block for a new robot starts from the URDF's joint names.
:func:`summarize_urdf` reads them the way :class:`~imac_data.core.robot.model.RobotModel` will (the
spec's default axis, a floating root held fixed, unsupported joint types refused) and
checks that every visual mesh resolves; :func:`recipe_block` turns that into a ``robot:``
block to edit::

    imac robot joints ROBOT.urdf [--package-dir NAME=PATH ...]

The block lists every movable, non-mimic joint in chain order (depth-first from the root
link, children in file order, so a bimanual rig lists one arm's chain, then the other's),
one ``joint_map`` entry per joint; the user reorders it to the dataset's
``observation.state`` / ``action`` order and deletes what the dataset does not record.
``gripper_links`` is a guess from each chain's tip (:func:`guess_gripper_links`) and says so.
"""

from __future__ import annotations

import json
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import yaml
import yourdfpy

from imac_data.core.robot.model import MOVABLE_JOINT_TYPES, kinematic_urdf, resolve_filename
from imac_data.errors import InputError

__all__ = ["JointInfo", "VisualLinkInfo", "UrdfSummary", "summarize_urdf", "recipe_block", "format_summary",
           "guess_gripper_links", "chain_order"]

# How a recipe entry converts a dataset value in other units to a joint position.
AFFINE_HINT = ("# An entry whose dataset values are not radians / metres (degrees, -100..100, a 0..1 gripper)\n"
               "# needs an affine map, position = offset + scale * value: {joint: JOINT, scale: S, offset: O}.")

# A joint or child link named so is a gripper's (guess_gripper_links).
GRIPPER_WORDS = re.compile(r"grip|jaw|finger|claw", re.IGNORECASE)


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
    joints: tuple[JointInfo, ...]  # movable joints, chain order (chain_order)
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


def chain_order(joints: Sequence, links: Sequence[str]) -> list:
    """``joints`` (objects with ``name``, ``parent``, ``child``; file order) depth-first from the
    root link(s), children in file order: each chain from its root to its tip, one arm's chain
    before the next arm's. Joints no root reaches (a malformed tree) follow in file order."""
    children: dict[str, list] = {}
    for j in joints:
        children.setdefault(j.parent, []).append(j)
    child_links = {j.child for j in joints}
    roots = [link for link in links if link not in child_links]
    out, seen = [], set()
    stack = [j for root in reversed(roots) for j in reversed(children.get(root, []))]
    while stack:
        j = stack.pop()
        if j.name in seen:  # a cycle: the model refuses it elsewhere; listed once here
            continue
        seen.add(j.name)
        out.append(j)
        stack += reversed(children.get(j.child, []))
    return out + [j for j in joints if j.name not in seen]


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
    for j in chain_order(urdf.robot.joints, [link.name for link in urdf.robot.links]):
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
    """The gripper links, guessed from each chain's tip, in chain order (links with visuals only).

    A chain's tip is a movable joint with no movable joint below it. A tip that looks like a
    gripper's (a name or child link with ``grip``, ``jaw``, ``finger`` or ``claw`` in it, a prismatic
    joint, or one in a mimic relation) gives every link below it; where it is the only such tip on
    its link (one moving jaw, as the SO-101's), the link it closes against, its parent, is the other
    jaw and is added. With no tip like that, each tip gives the tip link(s) below it."""
    below: dict[str, list[str]] = {}  # link -> child links
    joint_of_child: dict[str, str] = {}
    if urdf is None:
        urdf = yourdfpy.URDF.load(str(summary.path), build_scene_graph=False, load_meshes=False)
    for j in urdf.robot.joints:
        below.setdefault(j.parent, []).append(j.child)
        joint_of_child[j.child] = j.name
    movable = {j.name for j in summary.joints}
    leaders = {j.mimic[0] for j in summary.joints if j.mimic is not None}
    visual = {v.link for v in summary.visual_links}

    def subtree(link: str) -> list[str]:
        out, stack = [], [link]
        while stack:
            if (link := stack.pop()) not in out:  # a cycle is listed once
                out.append(link)
                stack += reversed(below.get(link, []))
        return out

    def gripper_like(j: JointInfo) -> bool:
        return (j.type == "prismatic" or j.mimic is not None or j.name in leaders
                or bool(GRIPPER_WORDS.search(j.name) or GRIPPER_WORDS.search(j.child)))

    tips = [j for j in summary.joints if not any(joint_of_child.get(link) in movable for link in subtree(j.child)[1:])]
    grippers = [j for j in tips if gripper_like(j)]
    links: list[str] = []

    def add(names) -> None:
        links.extend(n for n in names if n in visual and n not in links)

    if grippers:
        on_link: dict[str, int] = {}
        for j in grippers:
            on_link[j.parent] = on_link.get(j.parent, 0) + 1
        for j in grippers:
            add(([j.parent] if on_link[j.parent] == 1 else []) + subtree(j.child))
    else:
        for j in tips:
            sub = subtree(j.child)
            add([link for link in sub if not below.get(link) and link in visual] or sub)
    return links


def _yaml_scalar(text: str) -> str:
    """``text`` as a YAML flow scalar: plain where YAML reads it back unchanged, else quoted."""
    try:
        plain = yaml.safe_load(f"[{text}]") == [text]
    except yaml.YAMLError:
        plain = False
    return text if plain and not text.startswith("#") else json.dumps(text)


def _fmt(x: float | None) -> str:
    return "-" if x is None else f"{x:.6g}"


def format_summary(summary: UrdfSummary) -> str:
    lines = [f"URDF {summary.path}: robot {summary.name!r}, root link {summary.root}", "",
             f"movable joints ({len(summary.joints)}, chain order from the root):"]
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


def recipe_block(summary: UrdfSummary, gripper_links: Sequence[str] = (), joint_map: Sequence[dict] | None = None,
                 units: str = "") -> str:
    """A recipe ``robot:`` block to start from (YAML, with comments saying what to edit). ``joint_map``: entries
    ``{joint, scale, offset}`` already derived (a LeRobot robot's, in ``units``) instead of the URDF's joints."""
    out = [f"# Recipe `robot:` block for {summary.name!r}, to start from (imac robot joints).",
           "robot:",
           f"  urdf: {summary.path.resolve()}"]
    if summary.package_dirs:
        out.append("  package_dirs:")
        out += [f"    {name}: {Path(d).resolve()}" for name, d in summary.package_dirs]
    if joint_map is not None:
        out += [f"  # LeRobot's motors in the state's order, its values ({units}) to radians (docs/new-robot.md):",
                "  joint_map:"]
        out += [f"    - {{joint: {_yaml_scalar(e['joint'])}, scale: {e['scale']:.10g}, offset: {e['offset']:.10g}}}"
                for e in joint_map]
        guess = ", ".join(_yaml_scalar(link) for link in gripper_links)
        return "\n".join([*out, f"  gripper_links: [{guess}]  # guessed: the links at each chain's tip; check"]) + "\n"
    out += ["  # One entry per index of the dataset's observation.state / action vector, in that order:",
            "  # reorder, and delete the joints the dataset does not record (they stay at 0).",
            *("  " + line for line in AFFINE_HINT.splitlines()),
            "  joint_map:"]
    names = {j.name: _yaml_scalar(j.name) for j in summary.drivable}
    width = max((len(n) for n in names.values()), default=0)
    for j in summary.drivable:
        rng = "unlimited" if j.lower is None and j.upper is None else f"[{_fmt(j.lower)}, {_fmt(j.upper)}]"
        note = f"{j.type} {rng} {j.unit}"
        followers = summary.followers(j.name)
        if followers:
            note += f"; moves {', '.join(followers)} (mimic)"
        out.append(f"    - {names[j.name]:<{width}}  # {note}")
    if not summary.drivable:
        out.append("    []  # the URDF has no movable joint")
    guess = ", ".join(_yaml_scalar(link) for link in gripper_links)
    out.append(f"  gripper_links: [{guess}]  # guessed: the links at each chain's tip (the gripper); check")
    return "\n".join(out) + "\n"
