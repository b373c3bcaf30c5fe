"""LeRobot's joint units (imac_data/core/robot/lerobot_units.py) against LeRobot's own normalisation
(``MotorsBus._normalize`` of lerobot/motors/motors_bus.py, run on random calibrations and encoder ticks): the
joint map brings a recorded value back to the angle from the middle of the calibrated range, whichever units and
drive mode recorded it, and the gripper's 0..100 onto the URDF's range."""

from __future__ import annotations

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest
from lerobot.motors.motors_bus import Motor, MotorNormMode, MotorsBus
from lerobot.motors.motors_bus import MotorCalibration as LeRobotCalibration

from imac_data.core.robot.lerobot_units import (
    LEROBOT_ARMS,
    MotorCalibration,
    body_map,
    gripper_map,
    joint_map,
    read_calibration,
)
from imac_data.errors import InputError

RESOLUTION = 4096
MODES = {"degrees": MotorNormMode.DEGREES, "range_m100_100": MotorNormMode.RANGE_M100_100,
         "range_0_100": MotorNormMode.RANGE_0_100}


def lerobot_value(mode: str, cal: MotorCalibration, ticks: int) -> float:
    """What LeRobot records for ``ticks``: its own ``_normalize`` on a bus of one motor (no port opened)."""
    bus = SimpleNamespace(calibration={"m": LeRobotCalibration(**vars(cal))}, apply_drive_mode=True,
                          motors={"m": Motor(1, "sts3215", MODES[mode])}, model_resolution_table={"sts3215": RESOLUTION},
                          _id_to_name=lambda i: "m", _id_to_model=lambda i: "sts3215")
    return MotorsBus._normalize(bus, {1: ticks})[1]


def random_calibrations(n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    for _ in range(n):
        lo = int(rng.integers(0, 2000))
        hi = int(rng.integers(lo + 200, 4096))
        yield MotorCalibration(id=1, drive_mode=int(rng.integers(0, 2)), homing_offset=int(rng.integers(-2047, 2047)),
                               range_min=lo, range_max=hi), rng.integers(lo, hi + 1, size=5)


@pytest.mark.parametrize("units", ["degrees", "range_m100_100"])
def test_a_recorded_body_value_maps_back_to_the_angle_from_the_ranges_middle(units):
    for cal, ticks in random_calibrations(50):
        scale, offset = body_map(units, cal, RESOLUTION)
        for t in ticks:
            angle = offset + scale * lerobot_value(units, cal, int(t))
            want = (t - (cal.range_min + cal.range_max) / 2) * 2 * math.pi / (RESOLUTION - 1)
            assert angle == pytest.approx(want, abs=1e-9), (cal, t)


def test_the_gripper_maps_its_0_to_100_onto_the_urdf_range_from_the_lower_limit():
    lower, upper = -0.17453, 1.74533  # so101_new_calib's gripper joint
    scale, offset = gripper_map(lower, upper)
    for cal, ticks in random_calibrations(20, seed=1):
        cal = MotorCalibration(**{**vars(cal), "drive_mode": 0})
        for t in ticks:
            q = offset + scale * lerobot_value("range_0_100", cal, int(t))
            want = lower + (t - cal.range_min) / (cal.range_max - cal.range_min) * (upper - lower)
            assert q == pytest.approx(want, abs=1e-9)


def test_the_so101_joint_map_in_both_units_gives_one_robot(tmp_path):
    """The same ticks recorded in degrees and in -100..100 (with the calibration file) land on the same radians;
    -100..100 without the file is refused, naming the file LeRobot writes and where it lives."""
    arm = LEROBOT_ARMS["so101_follower"]
    limits = {m: (-1.9, 1.9) for m in arm.body} | {arm.gripper: (-0.17453, 1.74533)}
    cals = {m: cal for m, (cal, _) in zip((*arm.body, arm.gripper), random_calibrations(6, seed=2))}
    file = tmp_path / "my_arm.json"
    file.write_text(json.dumps({m: vars(c) for m, c in cals.items()}))
    calibration = read_calibration(file)
    assert calibration == cals
    degrees = joint_map("so101_follower", limits)
    ranged = joint_map("so101_follower", limits, units="range_m100_100", calibration=calibration)
    assert [e["joint"] for e in degrees] == [*arm.body, arm.gripper] == [e["joint"] for e in ranged]
    for d, r in zip(degrees[:-1], ranged[:-1]):
        cal = cals[d["joint"]]
        for t in (cal.range_min + 10, (cal.range_min + cal.range_max) // 2, cal.range_max - 10):
            a = d["offset"] + d["scale"] * lerobot_value("degrees", cal, t)
            b = r["offset"] + r["scale"] * lerobot_value("range_m100_100", cal, t)
            assert a == pytest.approx(b, abs=1e-9)
    assert degrees[-1] == ranged[-1] == {"joint": "gripper", "scale": pytest.approx(0.0191986), "offset": -0.17453}
    with pytest.raises(InputError, match=r"only through the robot's calibration file .*calibration/robots/"):
        joint_map("so101_follower", limits, units="range_m100_100")
    with pytest.raises(InputError, match=r"the URDF has no joints \['gripper'\]"):
        joint_map("so101_follower", {m: (-1, 1) for m in arm.body})


def test_a_damaged_calibration_file_is_refused_naming_the_file_and_motor(tmp_path):
    bad = tmp_path / "cal.json"
    bad.write_text(json.dumps({"shoulder_pan": {"id": 1, "drive_mode": 0, "range_min": 10, "range_max": 9,
                                                "homing_offset": 0}}))
    with pytest.raises(InputError, match=r"cal.json: motor 'shoulder_pan': range_max 9 is not above range_min 10"):
        read_calibration(bad)
    bad.write_text(json.dumps({"gripper": {"id": 6}}))
    with pytest.raises(InputError, match=r"cal.json: motor 'gripper': needs integer id"):
        read_calibration(bad)
    with pytest.raises(InputError, match=r"no such calibration file"):
        read_calibration(tmp_path / "missing.json")
