import os

import pytest

from imac_data.console import restore_scheduling, scheduling

# Before anything imports mujoco or dm_control: headless EGL rendering (Mesa on the CPU).
os.environ.setdefault("MUJOCO_GL", "egl")

_USUAL = scheduling()  # the scheduling the suite started with


@pytest.fixture(autouse=True)
def _usual_scheduling():
    """Tests and module fixtures that write with LeRobot's own writer as root leave the test process real-time
    (SVT-AV1; docs/building.md), and every later subprocess with it: each test starts and ends on the usual
    policy (before it, too: a module fixture is set up before this one)."""
    restore_scheduling(_USUAL)
    yield
    restore_scheduling(_USUAL)
