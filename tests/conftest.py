import os

# Before anything imports mujoco or dm_control: headless EGL rendering (Mesa on the CPU).
os.environ.setdefault("MUJOCO_GL", "egl")

import sys  # noqa: E402

# pybullet (an independent oracle for the Panda tests) has no cp312/cp313 wheel: pyproject.toml installs it on
# Python 3.11 only, whose CI run (make test) covers these tests (docs/lerobot.md, "Python versions").
PYBULLET_MISSING = sys.version_info >= (3, 12)
PYBULLET_REASON = ("pybullet 3.2.7 has no cp312/cp313 wheel, so Python 3.12+ environments go without it; "
                   "the Python 3.11 run (CI's make test) covers this test")
