"""The pose update of one camera and how a pose change reads, per axis.

A camera's pose is updated in its own axes (OpenCV: x right, y down, z forward):
``T_world_cam = T0_world_cam @ exp(xi)``, and for a camera mounted on a link
``T_link_cam = T0_link_cam @ exp(xi)``. The optimisers work in rounded units (cm,
degrees, focal percent: :data:`UNITS`); pose changes and errors are reported in the same
camera axes, translation in mm and rotation vector in degrees, so "z" is always along the view.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch

from imac_data.core.cameras import Camera

__all__ = ["UNITS", "AXES", "se3_exp", "apply_update", "pose_change"]

# Optimisation units: translation in cm, rotation in degrees, focal in percent, so one
# unit moves the image by a comparable amount and the optimisers see a round problem.
UNITS = np.array([0.01, 0.01, 0.01, math.radians(1.0), math.radians(1.0), math.radians(1.0), 0.01])
AXES = ("x_mm", "y_mm", "z_mm", "rx_deg", "ry_deg", "rz_deg")

# ----------------------------------------------------------------------------- SE(3)


def se3_exp(xi: torch.Tensor) -> torch.Tensor:
    """``(..., 6)`` twists ``(v, omega)`` (metres, radians) -> ``(..., 4, 4)`` rigid transforms
    (differentiable)."""
    v, w = xi[..., :3], xi[..., 3:6]
    A = torch.zeros(*xi.shape[:-1], 4, 4, dtype=xi.dtype, device=xi.device)
    A[..., 0, 1], A[..., 0, 2], A[..., 1, 2] = -w[..., 2], w[..., 1], -w[..., 0]
    A[..., 1, 0], A[..., 2, 0], A[..., 2, 1] = w[..., 2], -w[..., 1], w[..., 0]
    A[..., :3, 3] = v
    return torch.linalg.matrix_exp(A)


def _update_matrix(p: np.ndarray) -> np.ndarray:
    xi = torch.as_tensor(np.asarray(p[:6], dtype=np.float64) * UNITS[:6])
    return se3_exp(xi).numpy()


def apply_update(camera: Camera, p: Sequence[float]) -> Camera:
    """``camera`` moved by the update ``p`` (optimisation units: ``(x, y, z)`` cm, ``(rx, ry, rz)``
    degrees in the camera's axes, then optionally the focal change in percent)."""
    p = np.zeros(7) + np.pad(np.asarray(p, dtype=np.float64), (0, 7 - len(p)))
    M = _update_matrix(p)
    K = camera.K.copy()
    s = math.exp(p[6] * UNITS[6])
    K[0, :2] *= s
    K[1, 1] *= s
    if camera.is_mounted:  # the time offset is the camera's, not its pose's: it stays
        return Camera(camera.name, K, camera.width, camera.height, link=camera.link, T_link_cam=camera.T_link_cam @ M,
                      time_offset_s=camera.time_offset_s)
    return Camera(camera.name, K, camera.width, camera.height, T_world_cam=camera.T_world_cam @ M,
                  time_offset_s=camera.time_offset_s)


def _parent_pose(camera: Camera) -> np.ndarray:
    return camera.T_link_cam if camera.is_mounted else camera.T_world_cam


def pose_change(before: Camera | np.ndarray, after: Camera | np.ndarray) -> dict[str, float]:
    """Per-axis change from ``before`` to ``after`` in ``before``'s camera axes (OpenCV: x right,
    y down, z forward): translation of the camera centre in mm, rotation vector in degrees,
    plus the norms (``t_mm``, ``r_deg``). Takes two cameras (their ``T_world_cam`` or
    ``T_link_cam``) or two 4x4 camera-to-parent matrices."""
    from scipy.spatial.transform import Rotation

    A = _parent_pose(before) if isinstance(before, Camera) else np.asarray(before, dtype=np.float64)
    B = _parent_pose(after) if isinstance(after, Camera) else np.asarray(after, dtype=np.float64)
    D = np.linalg.inv(A) @ B
    t = D[:3, 3] * 1000.0
    r = np.degrees(Rotation.from_matrix(D[:3, :3]).as_rotvec())
    out = {k: float(v) for k, v in zip(AXES, (*t, *r))}
    out["t_mm"] = float(np.linalg.norm(t))
    out["r_deg"] = float(np.linalg.norm(r))
    return out
