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

import hashlib
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from imac_data.errors import InputError

UNITS = ("degrees", "range_m100_100")  # a body joint's; the gripper's is always range_0_100
GRIPPER_UNITS = "range_0_100"
# what each mode can record at all: the ranged modes clamp the ticks to range_min..range_max, so they stay within
# their ends; degrees takes the ticks unclamped, but both they and the range's middle lie within one turn's
# 0..resolution - 1, so a value in degrees is at most a turn from 0 (ticks recorded as they are go beyond)
VALUE_RANGES = {"degrees": (-360.0, 360.0), "range_m100_100": (-100.0, 100.0), GRIPPER_UNITS: (0.0, 100.0)}
VALUE_SLACK = 1e-3  # float32 storage of a value at an end
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


def read_calibration(path: str | Path, motors: tuple[str, ...] = ()) -> dict[str, MotorCalibration]:
    """LeRobot's calibration file (JSON, one entry per motor), checked: a clear error names the file and motor;
    ``motors``: the motors it must hold (a robot type's)."""
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
    absent = [m for m in motors if m not in out]
    if absent:
        raise InputError(f"{path}: no motors {absent} in it (the robot's motors are {list(motors)}): the calibration "
                         "file of another robot type?")
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


def convention(robot: str, units: str | None = None, calibration: str | Path | None = None) -> dict:
    """What a dataset records of the LeRobot units its joint map took (``imac.build.joint_units``): the robot
    type, the body's units (default: the type's), the gripper's, and the calibration file (path and sha256) that
    the -100..100 map came from, or None."""
    arm = LEROBOT_ARMS[robot]
    cal = None
    if calibration is not None:
        path = Path(calibration)
        cal = {"file": str(path.resolve()), "sha256": hashlib.sha256(path.read_bytes()).hexdigest()}
    return {"lerobot_robot": robot, "joints": [*arm.body, arm.gripper], "body": units or arm.units,
            "gripper": GRIPPER_UNITS, "calibration": cal}


def value_problems(conv: dict, lo, hi) -> list[str]:
    """The joint-vector entries whose recorded range ``lo[i]..hi[i]`` (``(D,)`` arrays) leaves what the units of
    convention ``conv`` (:func:`convention`) can record: one message per entry, naming its index, joint and units."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    joints = conv["joints"]
    problems = []
    for i, joint in enumerate(joints[:len(lo)]):
        units = conv["gripper"] if i == len(joints) - 1 else conv["body"]
        a, b = VALUE_RANGES[units]
        if lo[i] >= a - VALUE_SLACK and hi[i] <= b + VALUE_SLACK:
            continue
        problems.append(f"index {i} ({joint!r}, {units}): recorded {lo[i]:.5g}..{hi[i]:.5g}, outside the {a:g}..{b:g} "
                        f"LeRobot's {units} can record")
    return problems


def units_refusal(conv: dict, lo, hi, *, source: str, recipe: str) -> str | None:
    """The build's refusal when the recorded values of ``source`` contradict the recipe's LeRobot units (None when
    they do not): what is out, and what to check."""
    problems = value_problems(conv, lo, hi)
    if not problems:
        return None
    return (f"{source}: the recorded joint values contradict the LeRobot units of {recipe}'s robot (body "
            f"{conv['body']}, gripper {conv['gripper']}):\n  - " + "\n  - ".join(problems)
            + "\n  Set robot.units to the units the dataset was recorded in (degrees, or range_m100_100 with "
            "robot.calibration: the arm's calibration file), or check that source.state_key holds LeRobot's joint "
            "positions (docs/new-robot.md, \"LeRobot's joint units\")")


__all__ = ["GRIPPER_UNITS", "LEROBOT_ARMS", "LeRobotArm", "MotorCalibration", "UNITS", "VALUE_RANGES", "body_map",
           "convention", "gripper_map", "joint_map", "read_calibration", "units_refusal", "value_problems"]
