"""Motion images: the robot rendered from its URDF and forward kinematics into camera views.

Backends (:data:`BACKENDS`; a new one is one entry) implement :class:`~.base.Renderer`:

* ``open3d``: :class:`~.raycast.RaycastRenderer` casts rays with Open3D on the CPU against a scene built
  once, every link in its own frame (the CPU build's);
* ``opengl``: :class:`~.opengl.GLRenderer` rasterises the same triangles with OpenGL through EGL (Mesa's
  llvmpipe on a CPU), sampled and shaded the same way: a build's render stage about 0.74 times the ray
  caster's CPU at 480x640, none saved at 240x320 (the recipe's ``augment.renderer``);
* ``torch``: :class:`~.raster.RasterRenderer` rasterises the same triangles with torch, sampled and
  shaded the same way, on any torch device (``imac build --device cuda``).

``docs/dataset-format.md``, "How the robot is rendered", says what a motion image is."""

from __future__ import annotations

from imac_data.core.render.base import Renderer, RenderOutput, check_device
from imac_data.core.render.opengl import GLRenderer
from imac_data.core.render.raster import RasterRenderer
from imac_data.core.render.raycast import RaycastRenderer
from imac_data.core.robot.model import RobotModel
from imac_data.errors import InputError

__all__ = ["BACKENDS", "GLRenderer", "RasterRenderer", "RaycastRenderer", "RenderOutput", "Renderer", "check_device", "make_renderer"]

BACKENDS = {"open3d": RaycastRenderer, "opengl": GLRenderer, "torch": RasterRenderer}


def make_renderer(robot: RobotModel, backend: str = "open3d", **options) -> Renderer:
    """A renderer for ``robot`` by backend name (``"open3d"``, the default, ``"opengl"`` or ``"torch"``)."""
    if backend not in BACKENDS:
        raise InputError(f"unknown renderer backend {backend!r}; available: {sorted(BACKENDS)}")
    return BACKENDS[backend](robot, **options)
