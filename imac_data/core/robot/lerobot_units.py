"""LeRobot's joint units, and the affine maps that bring them to a URDF's radians (a recipe's joint map).

A LeRobot robot records each motor in its normalisation mode (``MotorNormMode``, applied by
``MotorsBus._normalize`` in ``lerobot/motors/motors_bus.py``) from the calibrated range ``range_min``..``range_max``
of its encoder ticks, ``resolution`` ticks a turn (4096 for the SO-100/SO-101's Feetech STS3215 and the Koch's
Dynamixels):

* ``degrees``: ``(ticks - mid) * 360 / (resolution - 1)``, ``mid = (range_min + range_max) / 2`` (``drive_mode`` is
  not applied);
* ``range_m100_100``: ``(ticks - range_min) / (range_max - range_min) * 200 - 100``, negated with ``drive_mode``;
* ``range_0_100``: ``(ticks - range_min) / (range_max - range_min) * 100``, ``100 - x`` with ``drive_mode``.

Each is affine in the ticks, so the angle from the middle of the calibrated range is affine in the recorded value:
``pi / 180`` a unit for degrees; ``(range_max - range_min) / 200 * 2 pi / (resolution - 1)`` a unit for
-100..100, its sign ``drive_mode``'s, which only the robot's calibration file gives. A URDF made for LeRobot's
degrees (``so101_new_calib``) puts each joint's zero at that middle, so the offset is 0. The gripper's 0..100 maps
onto the URDF's gripper range, 0 at its lower limit. ``docs/new-robot.md`` says what was checked (simulation and
LeRobot's own ``_normalize``), and what was not (a physical arm)."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

from imac_data.errors import InputError

UNITS = ("degrees", "range_m100_100")  # a body joint's; the gripper's is always range_0_100
CALIBRATION_HINT = ("LeRobot writes it when the arm is calibrated, as <id>.json under "
                    "$HF_LEROBOT_CALIBRATION/robots/<robot type>/: by default "
                    "~/.cache/huggingface/lerobot/calibration/robots/so101_follower/<id>.json for an SO-101 "
                    "(so_follower/<id>.json from LeRobot 0.4 on, koch_follower/<id>.json for a Koch), <id> the "
                    "robot's --robot.id")


@dataclass(frozen=True)
class LeRobotArm:
    """A LeRobot robot type's motors, as ``lerobot/robots/<type>/`` defines them."""

    body: tuple[str, ...]  # body joints, in the state's order
    gripper: str
    units: str  # the body's default (the config's ``use_degrees``)
    resolution: int = 4096  # encoder ticks a turn


_SO_JOINTS = ("shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll")
LEROBOT_ARMS = {
    "so101_follower": LeRobotArm(_SO_JOINTS, "gripper", "degrees"),  # use_degrees: True since LeRobot 0.4
    "so100_follower": LeRobotArm(_SO_JOINTS, "gripper", "degrees"),
    "koch_follower": LeRobotArm(_SO_JOINTS, "gripper", "range_m100_100"),  # use_degrees: False
}


@dataclass(frozen=True)
class MotorCalibration:
    """One motor's entry of LeRobot's calibration file."""

    id: int
    drive_mode: int
    homing_offset: int
    range_min: int
    range_max: int


def read_calibration(path: str | Path) -> dict[str, MotorCalibration]:
    """LeRobot's calibration file (JSON, one entry per motor), checked: a clear error names the file and motor."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(f"{path}: no such calibration file ({CALIBRATION_HINT})") from None
    except (OSError, json.JSONDecodeError) as e:
        raise InputError(f"{path}: not a readable LeRobot calibration file ({e})") from None
    out = {}
    for motor, entry in (data.items() if isinstance(data, dict) else ()):
        try:
            out[motor] = MotorCalibration(**{k: int(entry[k]) for k in MotorCalibration.__dataclass_fields__})
        except (KeyError, TypeError, ValueError) as e:
            raise InputError(f"{path}: motor {motor!r}: needs integer id, drive_mode, homing_offset, range_min and "
                             f"range_max ({type(e).__name__}: {e})") from None
        if out[motor].range_max <= out[motor].range_min:
            raise InputError(f"{path}: motor {motor!r}: range_max {out[motor].range_max} is not above range_min "
                             f"{out[motor].range_min}")
    if not out:
        raise InputError(f"{path}: no motors in it (a LeRobot calibration file maps motor names to their ranges)")
    return out


def body_map(units: str, calibration: MotorCalibration | None = None, resolution: int = 4096) -> tuple[float, float]:
    """``(scale, offset)`` with ``radians = offset + scale * value`` from the middle of the calibrated range."""
    if units == "degrees":
        return math.pi / 180.0, 0.0
    if units != "range_m100_100":
        raise InputError(f"LeRobot units {units!r}: one of {list(UNITS)} for a body joint")
    if calibration is None:
        raise InputError("joint values in -100..100 (LeRobot's range_m100_100 units) map to angles only through the "
                         "robot's calibration file "
                         f"(range_min, range_max, drive_mode per motor): {CALIBRATION_HINT}")
    scale = (calibration.range_max - calibration.range_min) / 200.0 * 2.0 * math.pi / (resolution - 1)
    return (-scale if calibration.drive_mode else scale), 0.0


def gripper_map(lower: float, upper: float) -> tuple[float, float]:
    """``(scale, offset)`` of the gripper's 0..100 onto the URDF joint's range, 0 at ``lower``."""
    return (upper - lower) / 100.0, lower


def joint_map(robot: str, joints: dict[str, tuple[float, float]], *, units: str | None = None,
              calibration: dict[str, MotorCalibration] | None = None) -> list[dict]:
    """A recipe's joint map for a LeRobot ``robot`` type recorded in ``units`` (default: the type's): one
    ``{joint, scale, offset}`` per motor, in the state's order. ``joints``: the URDF's joints and their limits
    ``(lower, upper)``, named as LeRobot names the motors."""
    if robot not in LEROBOT_ARMS:
        raise InputError(f"--lerobot-robot {robot!r}: one of {sorted(LEROBOT_ARMS)}")
    arm = LEROBOT_ARMS[robot]
    missing = [m for m in (*arm.body, arm.gripper) if m not in joints]
    if missing:
        raise InputError(f"the URDF has no joints {missing} (LeRobot's {robot} names its motors {[*arm.body, arm.gripper]})")
    units = units or arm.units
    if calibration is not None:
        absent = [m for m in (*arm.body, arm.gripper) if m not in calibration]
        if absent:
            raise InputError(f"the calibration file has no motors {absent}")
    out = [dict(zip(("joint", "scale", "offset"), (m, *body_map(units, (calibration or {}).get(m), arm.resolution))))
           for m in arm.body]
    return out + [dict(zip(("joint", "scale", "offset"), (arm.gripper, *gripper_map(*joints[arm.gripper]))))]


__all__ = ["LEROBOT_ARMS", "LeRobotArm", "MotorCalibration", "UNITS", "body_map", "gripper_map", "joint_map",
           "read_calibration"]
