"""A robot description as files: the URDF plus exactly the meshes it uses, self-contained.

A built dataset carries its robot under ``meta/imac/robot/`` (:data:`DESCRIPTION_DIR`) so
that anyone who downloads it can rebuild its controls, or render the robot online, with no
other file (:meth:`imac_data.core.rig.Rig.from_info`). The copy is:

* ``robot.urdf``: the URDF with every ``<mesh filename=...>`` (visual and collision)
  rewritten to ``meshes/<file name>``, relative to the URDF. Nothing else changes, except
  that a ``<collision>`` whose mesh cannot be found is left out, with a warning: we render
  visual geometry only, and many descriptions ship without their collision meshes;
* ``meshes/``: the mesh files those references resolved to (``package://``, ``file://``,
  absolute or URDF-relative paths), byte for byte.

Packaging is a fixed point: packaging an already packaged description gives the same
URDF text (and hash), which is what makes ``Rig.from_info`` -> ``to_info`` an exact round
trip. The manifest (:func:`description_manifest`) records the sha256 of every file, so a
reader can tell a complete, unmodified copy from a damaged one (:func:`check_description`).
"""

from __future__ import annotations

import hashlib
import os
import shutil
import uuid
import warnings
import xml.etree.ElementTree as ET
from pathlib import Path

from imac_data.core.robot.model import resolve_filename
from imac_data.errors import InputError
from imac_data.layout import DESCRIPTION_DIR, MESH_DIR, URDF_NAME

__all__ = ["packaged_description", "description_manifest", "write_description",
           "check_description"]


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def packaged_description(robot) -> tuple[str, dict[str, Path]]:
    """``(URDF text with mesh references rewritten, {relative path: source file})`` of a
    :class:`~imac_data.core.robot.model.RobotModel`."""
    config = robot.config
    root = ET.fromstring(robot.urdf_text.encode())
    _drop_missing_collision_meshes(root, config)
    files: dict[str, Path] = {}
    rel_of: dict[Path, str] = {}
    for mesh in root.iter("mesh"):
        fname = mesh.get("filename")
        if not fname:
            raise InputError(f"robot {config.name!r}: a <mesh> in {config.urdf_path} has no filename")
        src = resolve_filename(fname, config.urdf_path, dict(config.package_dirs)).resolve()
        if not src.is_file():
            raise InputError(f"robot {config.name!r}: mesh {fname!r} in {config.urdf_path} resolves to {src}, "
                             "which does not exist")
        if src not in rel_of:
            rel = f"{MESH_DIR}/{src.name}"
            if rel in files:  # two meshes of one name in different directories: name by content, so
                # that the packaged URDF does not depend on where the source tree lives
                rel = f"{MESH_DIR}/{src.stem}_{_sha256(src.read_bytes())[:12]}{src.suffix}"
            rel_of[src], files[rel] = rel, src
        mesh.set("filename", rel_of[src])
    return ET.tostring(root, encoding="unicode"), files


def _drop_missing_collision_meshes(root: ET.Element, config) -> None:
    for link in root.iter("link"):
        for collision in link.findall("collision"):
            mesh = collision.find("geometry/mesh")
            if mesh is None:
                continue
            fname = mesh.get("filename") or ""
            try:
                found = bool(fname) and resolve_filename(fname, config.urdf_path, dict(config.package_dirs)).is_file()
            except InputError:  # a package the config does not map
                found = False
            if not found:
                warnings.warn(f"robot {config.name!r}: collision mesh {fname!r} of link {link.get('name')!r} in "
                              f"{config.urdf_path} was not found; the dataset's copy of the URDF leaves that "
                              "<collision> out (imac renders visual meshes only)", stacklevel=2)
                link.remove(collision)


def description_manifest(robot) -> dict:
    """What ``info.json`` records of the packaged description: where it lives in the
    dataset, the sha256 of the URDF and of every mesh, and the total size in bytes."""
    text, files = packaged_description(robot)
    data = text.encode()
    hashes = {rel: _sha256(path.read_bytes()) for rel, path in sorted(files.items())}
    size = len(data) + sum(path.stat().st_size for path in files.values())
    return {"path": f"{DESCRIPTION_DIR}/{URDF_NAME}", "urdf_sha256": _sha256(data), "files": hashes, "bytes": size}


def description_bytes(robot) -> int:
    """The size on disk of ``robot``'s packaged description (URDF and meshes)."""
    text, files = packaged_description(robot)
    return len(text.encode()) + sum(src.stat().st_size for src in files.values())


def write_description(robot, dest: Path) -> dict:
    """Write the packaged description of ``robot`` into the directory ``dest`` (created
    atomically: a temporary sibling renamed into place; an existing ``dest`` is replaced).
    Returns the manifest."""
    dest = Path(dest)
    text, files = packaged_description(robot)
    tmp = dest.with_name(f".{dest.name}.{uuid.uuid4().hex[:8]}.tmp")
    try:
        (tmp / MESH_DIR).mkdir(parents=True)
        (tmp / URDF_NAME).write_text(text)
        for rel, src in files.items():
            shutil.copyfile(src, tmp / rel)
        if dest.exists():
            shutil.rmtree(dest)
        os.rename(tmp, dest)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return description_manifest_of_dir(dest)


def description_manifest_of_dir(directory: Path) -> dict:
    """The manifest of a packaged description on disk (hashes of the files as they are)."""
    directory = Path(directory)
    urdf = directory / URDF_NAME
    if not urdf.is_file():
        raise InputError(f"no robot description at {urdf}")
    data = urdf.read_bytes()
    files = {p.relative_to(directory).as_posix(): p for p in sorted((directory / MESH_DIR).rglob("*")) if p.is_file()}
    return {"path": f"{DESCRIPTION_DIR}/{URDF_NAME}", "urdf_sha256": _sha256(data),
            "files": {rel: _sha256(p.read_bytes()) for rel, p in files.items()},
            "bytes": len(data) + sum(p.stat().st_size for p in files.values())}


def check_description(directory: Path, manifest: dict, where: str = "robot description") -> None:
    """Raise :class:`InputError` unless ``directory`` holds exactly the files of ``manifest``
    with the recorded hashes (a missing, extra or modified file is named)."""
    found = description_manifest_of_dir(directory)
    if found["urdf_sha256"] != manifest.get("urdf_sha256"):
        raise InputError(f"{where}: {Path(directory) / URDF_NAME} differs from the recorded one "
                         f"(sha256 {found['urdf_sha256'][:12]}..., recorded {str(manifest.get('urdf_sha256'))[:12]}...)")
    want, have = manifest.get("files", {}), found["files"]
    missing = sorted(set(want) - set(have))
    if missing:
        raise InputError(f"{where}: file(s) {missing} missing under {directory}")
    changed = sorted(k for k in want if have[k] != want[k])
    if changed:
        raise InputError(f"{where}: file(s) {changed} under {directory} differ from the recorded ones")
    extra = sorted(set(have) - set(want))
    if extra:
        raise InputError(f"{where}: unexpected file(s) {extra} under {directory}")
