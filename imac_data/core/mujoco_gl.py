"""MuJoCo, imported in one place with a headless GL default.

MuJoCo picks its GL backend when it is first imported, so every module of ours imports it
from here: EGL (Mesa on the CPU) unless ``MUJOCO_GL`` says otherwise, so nothing needs a
display.
"""

import os

os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco  # noqa: E402  (after MUJOCO_GL)

__all__ = ["mujoco"]
