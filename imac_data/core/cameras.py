"""Pinhole cameras: intrinsics, fixed and link-mounted extrinsics, projection.

Conventions (docs/dataset-format.md):

* Extrinsics are **camera-to-world** 4x4 matrices in the **OpenCV** camera frame
  (x right, y down, z forward). MuJoCo/OpenGL cameras (looking down -z, y up) are
  converted once, at the boundary, with :func:`opengl_to_opencv`.
* ``K`` is the 3x3 pixel matrix of the stored image resolution, with pixel
  centres at integer coordinates (pixel ``(0, 0)`` covers ``[-0.5, 0.5]^2``).
  :func:`rescale_intrinsics` is the only place where K follows an image resize.
* A camera is *fixed* (constant ``T_world_cam``) or *mounted* on a robot link:
  ``T_world_cam(t) = FK(q_t)[link] @ T_link_cam``.
* ``time_offset_s``: the camera's frame stamped ``t`` shows the robot at the joint states of
  ``t + time_offset_s`` (negative: the camera lags); 0, the default, is left out of the files.

The math is torch (batched, any leading shape, CPU or CUDA) because the world
model calls it online; calibration files are JSON.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from imac_data.errors import InputError

# Flips the y and z camera axes: OpenGL (y up, looking down -z) <-> OpenCV (y down, +z).
_GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


def opengl_to_opencv(T_world_cam_gl: np.ndarray) -> np.ndarray:
    """Camera-to-world pose of an OpenGL/MuJoCo camera -> the same camera in OpenCV axes."""
    return np.asarray(T_world_cam_gl, dtype=np.float64) @ _GL_TO_CV


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera pose (OpenCV axes) at ``eye`` looking at ``target``, with ``up`` pointing up in the
    image; all in one parent frame (the world for a fixed camera, the link for a mounted one)."""
    eye = np.asarray(eye, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - eye
    x = np.cross(z, np.asarray(up, dtype=np.float64))
    if not (np.linalg.norm(z) > 0 and np.linalg.norm(x) > 1e-9 * np.linalg.norm(z)):
        raise InputError(f"look_at: eye {eye.tolist()} and target {list(target)} must differ, and the viewing "
                         f"direction must not be parallel to up {list(up)}")
    z /= np.linalg.norm(z)
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, np.cross(z, x), z, eye
    return T


def intrinsics_from_fovy(fovy_deg: float, width: int, height: int) -> np.ndarray:
    """K of an ideal pinhole with vertical field of view ``fovy_deg`` and square pixels
    (MuJoCo's camera model); the principal point is the image centre."""
    fy = 0.5 * height / math.tan(math.radians(fovy_deg) / 2.0)
    return np.array(
        [[fy, 0.0, (width - 1) / 2.0], [0.0, fy, (height - 1) / 2.0], [0.0, 0.0, 1.0]]
    )


def rescale_intrinsics(K: np.ndarray, from_hw: tuple[int, int], to_hw: tuple[int, int]) -> np.ndarray:
    """K for the same camera after resizing its image from ``from_hw`` to ``to_hw`` (H, W).

    Pixel edges scale, pixel centres do not: ``c' = (c + 0.5) * s - 0.5``.
    """
    sy = to_hw[0] / from_hw[0]
    sx = to_hw[1] / from_hw[1]
    K = np.array(K, dtype=np.float64, copy=True)
    K[0, 0] *= sx
    K[0, 1] *= sx
    K[1, 1] *= sy
    K[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
    K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
    return K


@dataclass(frozen=True)
class Camera:
    """One camera of a rig. Exactly one of ``T_world_cam`` (fixed) or ``link`` +
    ``T_link_cam`` (mounted) is set.

    Checked when made (a calibration file, a dataset's ``info.json``), with an
    :class:`InputError` naming the camera and the field: the pose is rigid (rotation
    orthonormal with det +1 within :data:`CALIBRATION_RIGID_TOL`, last row [0, 0, 0, 1]),
    fx, fy > 0, the principal point lies inside the image. Whether ``link`` exists is the
    rig's check (:class:`~imac_data.core.rig.Rig`), which knows the robot."""

    name: str
    K: np.ndarray
    width: int
    height: int
    T_world_cam: np.ndarray | None = None
    link: str | None = None
    T_link_cam: np.ndarray | None = field(default=None)
    time_offset_s: float = 0.0  # the frame stamped t shows the joint states of t + time_offset_s

    def __post_init__(self) -> None:
        object.__setattr__(self, "K", _matrix(self.K, (3, 3), f"camera {self.name!r} K"))
        off = self.time_offset_s
        if isinstance(off, bool) or not isinstance(off, (int, float)) or not math.isfinite(off) or abs(off) > 10.0:
            raise InputError(f"camera {self.name!r} time_offset_s: a number of seconds within +-10, got {off!r}")
        object.__setattr__(self, "time_offset_s", float(off))
        if (self.T_world_cam is None) == (self.link is None):
            raise InputError(
                f"camera {self.name!r}: give either T_world_cam (fixed) or link + T_link_cam (mounted)"
            )
        if self.T_world_cam is not None:
            object.__setattr__(
                self, "T_world_cam", _matrix(self.T_world_cam, (4, 4), f"camera {self.name!r} T_world_cam")
            )
        else:
            if self.T_link_cam is None:
                raise InputError(f"camera {self.name!r} is mounted on {self.link!r} but has no T_link_cam")
            object.__setattr__(
                self, "T_link_cam", _matrix(self.T_link_cam, (4, 4), f"camera {self.name!r} T_link_cam")
            )
        if self.width <= 0 or self.height <= 0:
            raise InputError(f"camera {self.name!r}: width and height must be positive")
        _check_intrinsics(self.name, self.K, self.width, self.height)
        pose, what = (self.T_world_cam, "T_world_cam") if self.link is None else (self.T_link_cam, "T_link_cam")
        why = rigid_problem(pose, CALIBRATION_RIGID_TOL)
        if why:
            raise InputError(f"camera {self.name!r} {what}: {why}; a pose must be a rigid transform")

    @property
    def is_mounted(self) -> bool:
        return self.link is not None

    def rescaled(self, width: int, height: int) -> Camera:
        """The same camera with its image resized to ``width`` x ``height``."""
        K = rescale_intrinsics(self.K, (self.height, self.width), (height, width))
        return Camera(self.name, K, width, height, self.T_world_cam, self.link, self.T_link_cam, self.time_offset_s)

    def for_images(self, height: int, width: int, *, where: str = "images") -> Camera:
        """This camera for images of ``height`` x ``width``: itself, or rescaled when the
        calibration was made at another resolution of the same aspect ratio (K follows);
        any other size is an :class:`InputError` naming the camera."""
        h, w = int(height), int(width)
        if (h, w) == (self.height, self.width):
            return self
        if not same_aspect((h, w), (self.height, self.width)):
            raise InputError(f"camera {self.name!r}: {where} are {h}x{w} (HxW) but its calibration is for "
                             f"{self.height}x{self.width}, another aspect ratio; calibrate at the recorded size")
        return self.rescaled(w, h)

    def pose(self, link_poses: Mapping[str, torch.Tensor] | None = None, *,
             batch_shape: tuple[int, ...] = (), device=None, dtype=torch.float32) -> torch.Tensor:
        """Camera-to-world pose(s), shape ``(*batch, 4, 4)``.

        Mounted cameras need ``link_poses`` (link name -> ``(*batch, 4, 4)`` world poses,
        as returned by forward kinematics); fixed cameras broadcast to ``batch_shape``.
        """
        if self.link is None:
            T = torch.as_tensor(self.T_world_cam, dtype=dtype, device=device)
            return T.expand(*batch_shape, 4, 4)
        if link_poses is None or self.link not in link_poses:
            raise InputError(
                f"camera {self.name!r} is mounted on link {self.link!r}, which the robot model does not have"
            )
        T_wl = link_poses[self.link]
        return T_wl @ torch.as_tensor(self.T_link_cam, dtype=T_wl.dtype, device=T_wl.device)

    def to_dict(self) -> dict:
        d = {"K": self.K.tolist(), "width": self.width, "height": self.height}
        if self.link is None:
            d["T_world_cam"] = self.T_world_cam.tolist()
        else:
            d["link"] = self.link
            d["T_link_cam"] = self.T_link_cam.tolist()
        if self.time_offset_s:  # absent = 0: files without an offset stay as they were
            d["time_offset_s"] = self.time_offset_s
        return d


CALIBRATION_RIGID_TOL = 1e-3  # |R R^T - I| and |det R - 1| of a calibration's poses (hand-typed decimals pass)
ASPECT_TOL = 0.01  # relative: sizes of one aspect ratio up to rounding of a resize


def same_aspect(a_hw: tuple[int, int], b_hw: tuple[int, int]) -> bool:
    """Whether two (H, W) image sizes have the same aspect ratio, up to the rounding of a resize."""
    ra, rb = a_hw[0] / a_hw[1], b_hw[0] / b_hw[1]
    return abs(ra - rb) <= ASPECT_TOL * rb


def rigid_problem(T, tol: float) -> str | None:
    """Why the pose(s) ``T`` ``(..., 4, 4)`` are not rigid transforms (None if they are):
    last row [0, 0, 0, 1], rotation orthonormal and det +1 within ``tol``."""
    T = np.asarray(T, dtype=np.float64).reshape(-1, 4, 4)
    R = T[:, :3, :3]
    bad_row = np.abs(T[:, 3] - [0, 0, 0, 1]).max(-1) > 1e-6
    if bad_row.any():
        return f"last row is {T[np.argmax(bad_row), 3].tolist()}, not [0, 0, 0, 1]"
    ortho = np.abs(R @ R.transpose(0, 2, 1) - np.eye(3)).max()
    if ortho > tol:
        return f"rotation is not orthonormal (|R R^T - I| = {ortho:.2g} > {tol:g})"
    det = np.linalg.det(R)
    if np.abs(det - 1).max() > tol:
        return f"rotation has det {det[np.argmax(np.abs(det - 1))]:.4f}, not +1 (a reflection or a scale)"
    return None


def _check_intrinsics(name: str, K: np.ndarray, width: int, height: int) -> None:
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        raise InputError(f"camera {name!r} K: focal lengths fx={K[0, 0]:g}, fy={K[1, 1]:g} must be > 0")
    if not (-0.5 <= K[0, 2] <= width - 0.5 and -0.5 <= K[1, 2] <= height - 0.5):
        raise InputError(f"camera {name!r} K: principal point ({K[0, 2]:g}, {K[1, 2]:g}) lies outside its "
                         f"{width}x{height} (WxH) image")
    if np.abs(K[2] - [0, 0, 1]).max() > 1e-9 or K[1, 0] != 0:
        raise InputError(f"camera {name!r} K: must be [[fx, s, cx], [0, fy, cy], [0, 0, 1]], got {K.tolist()}")


def _matrix(value, shape: tuple[int, int], what: str) -> np.ndarray:
    try:
        m = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise InputError(f"{what}: not a numeric matrix ({e})") from None
    if m.shape != shape:
        raise InputError(f"{what}: expected shape {shape}, got {m.shape}")
    if not np.all(np.isfinite(m)):
        raise InputError(f"{what}: contains NaN or inf")
    return m


# --------------------------------------------------------------------------- math


def project(points_world: torch.Tensor, K: torch.Tensor, T_world_cam: torch.Tensor
            ) -> tuple[torch.Tensor, torch.Tensor]:
    """Project world points to pixels.

    points_world ``(*B, N, 3)``; K ``(*B, 3, 3)``; T_world_cam ``(*B, 4, 4)`` (camera-to-world,
    OpenCV). Returns ``uv (*B, N, 2)`` in pixel coordinates and camera z-depth ``(*B, N)``.
    Points behind the camera get ``z <= 0``; their uv are meaningless.
    """
    T_cam_world = torch.linalg.inv(T_world_cam)
    p_cam = points_world @ T_cam_world[..., :3, :3].transpose(-1, -2) + T_cam_world[..., None, :3, 3]
    z = p_cam[..., 2]
    pix = p_cam @ K.transpose(-1, -2)
    uv = pix[..., :2] / z[..., None]
    return uv, z


def pixel_grid(height: int, width: int, device=None, dtype=torch.float32) -> torch.Tensor:
    """``(H, W, 2)`` tensor of (u, v) pixel-centre coordinates."""
    v, u = torch.meshgrid(
        torch.arange(height, device=device, dtype=dtype),
        torch.arange(width, device=device, dtype=dtype),
        indexing="ij",
    )
    return torch.stack([u, v], dim=-1)


def pixel_rays(K: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Camera-frame rays ``K^-1 [u, v, 1]`` through every pixel centre (integer ``u, v``),
    shape ``(*B, H*W, 3)`` for ``K (*B, 3, 3)``, row-major pixels, z component exactly 1,
    so ``depth * ray`` is the pixel's point at planar z-depth ``depth``. The one place
    pixels become rays: :func:`backproject`, the contact streams' scene and robot points.
    """
    v, u = torch.meshgrid(torch.arange(height, device=K.device, dtype=K.dtype),
                          torch.arange(width, device=K.device, dtype=K.dtype), indexing="ij")
    pix = torch.stack([u, v, torch.ones_like(u)], dim=-1).reshape(-1, 3)
    rays = pix @ torch.linalg.inv(K).transpose(-1, -2)
    rays[..., 2] = 1.0
    return rays


def backproject(depth: torch.Tensor, K: torch.Tensor, T_world_cam: torch.Tensor) -> torch.Tensor:
    """Lift a z-depth map ``(*B, H, W)`` to world points ``(*B, H, W, 3)``.

    Invalid depth (0 or non-finite) yields points at the camera centre along the ray
    scaled by that value; callers mask them with ``depth > 0``.
    """
    H, W = depth.shape[-2:]
    rays = pixel_rays(K.to(depth.dtype), H, W).reshape(*K.shape[:-2], H, W, 3)  # (*B, H, W, 3)
    p_cam = rays * depth[..., None]
    R = T_world_cam[..., None, :3, :3]
    t = T_world_cam[..., None, None, :3, 3]
    return p_cam @ R.transpose(-1, -2) + t


# --------------------------------------------------------------------------- files


def save_calibration(path: str | Path, cameras: Mapping[str, Camera]) -> None:
    """Write a rig calibration as JSON: ``{"cameras": {name: {K, width, height, T_world_cam | link, T_link_cam
    [, time_offset_s]}}}``."""
    payload = {
        "convention": "camera-to-world, OpenCV axes (x right, y down, z forward), metres",
        "cameras": {name: cam.to_dict() for name, cam in cameras.items()},
    }
    Path(path).write_text(json.dumps(payload, indent=2))


def camera_from_dict(name: str, entry, where: str = "camera") -> Camera:
    """A :class:`Camera` from its :meth:`Camera.to_dict` form (calibration files, ``info.json``)."""
    if not isinstance(entry, dict):
        raise InputError(f"{where}: expected a mapping")
    missing = [k for k in ("K", "width", "height") if k not in entry]
    if missing:
        raise InputError(f"{where}: missing key(s) {missing}")
    for key in ("width", "height"):  # int() would truncate 160.5 or parse "160"; a size is a whole number
        v = entry[key]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not float(v).is_integer():
            raise InputError(f"{where}.{key}: expected a whole number of pixels, got {v!r}")
    try:
        return Camera(name=name, K=entry["K"], width=int(entry["width"]), height=int(entry["height"]),
                      T_world_cam=entry.get("T_world_cam"), link=entry.get("link"), T_link_cam=entry.get("T_link_cam"),
                      time_offset_s=entry.get("time_offset_s", 0.0))
    except InputError as e:
        raise InputError(f"{where}: {e}") from None
    except (TypeError, ValueError) as e:
        raise InputError(f"{where}: {e}") from None


def load_calibration(path: str | Path) -> dict[str, Camera]:
    """Read a calibration JSON written by :func:`save_calibration` (or by hand in that schema)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"calibration file not found: {path}")
    try:
        payload = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise InputError(f"{path}: not valid JSON ({e})") from None
    if not isinstance(payload, dict) or not isinstance(payload.get("cameras"), dict):
        raise InputError(f"{path}: expected a top-level 'cameras' mapping")
    cameras = {name: camera_from_dict(name, entry, f"{path}: cameras.{name}")
               for name, entry in payload["cameras"].items()}
    if not cameras:
        raise InputError(f"{path}: no cameras")
    return cameras
