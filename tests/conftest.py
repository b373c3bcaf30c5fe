import os

import pytest

from imac_data.console import scheduling_kept

# Before anything imports mujoco or dm_control: headless EGL rendering (Mesa on the CPU).
os.environ.setdefault("MUJOCO_GL", "egl")


@pytest.fixture(autouse=True)
def _scheduling_restored():
    """Tests that write with LeRobot's own writer as root leave the test process real-time (SVT-AV1;
    docs/building.md), and every later test's subprocesses with it: each test starts from the usual policy."""
    with scheduling_kept():
        yield
