import os

import pytest

from imac_data.console import cpu_cores, restore_scheduling, scheduling

# Before anything imports mujoco or dm_control: headless EGL rendering (Mesa on the CPU).
os.environ.setdefault("MUJOCO_GL", "egl")
# Each pytest-xdist process, and every process it starts, gets its share of the cores for OpenMP's (and so torch's)
# thread pools: two processes each spinning a pool of both cores made the 2-core suite 13 % slower (694 s, 616 s)
# (docs/verification.md, "The test suite"). A value the caller set is kept.
_WORKERS = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
if _WORKERS > 1:
    os.environ.setdefault("OMP_NUM_THREADS", str(max(1, cpu_cores() // _WORKERS)))

_USUAL = scheduling()  # the scheduling the suite started with


@pytest.fixture(autouse=True)
def _usual_scheduling():
    """Tests and module fixtures that write with LeRobot's own writer as root leave the test process real-time
    (SVT-AV1; docs/building.md), and every later subprocess with it: each test starts and ends on the usual
    policy (before it, too: a module fixture is set up before this one)."""
    restore_scheduling(_USUAL)
    yield
    restore_scheduling(_USUAL)
