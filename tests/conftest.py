import os

import pytest

# Before anything imports mujoco or dm_control: headless EGL rendering (Mesa on the CPU).
os.environ.setdefault("MUJOCO_GL", "egl")

# the scheduling the suite started with
_USUAL = (os.sched_getscheduler(0), os.sched_getparam(0).sched_priority) if hasattr(os, "sched_getscheduler") else None


def _back_to_usual() -> None:
    if _USUAL is not None and (os.sched_getscheduler(0), os.sched_getparam(0).sched_priority) != _USUAL:
        os.sched_setscheduler(0, _USUAL[0], os.sched_param(_USUAL[1]))


@pytest.fixture(autouse=True)
def _usual_scheduling():
    """Tests and module fixtures that write with LeRobot's own writer as root leave the test process real-time
    (SVT-AV1; docs/building.md), and every later subprocess with it: each test starts and ends on the usual
    policy (before it, too: a module fixture is set up before this one)."""
    _back_to_usual()
    yield
    _back_to_usual()
