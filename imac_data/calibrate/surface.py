"""Point clouds for calibration from nothing: the robot's surface at recorded joint states,
depth maps lifted with a trial focal length, and the robot's pixels found in depth alone.

Everything here is plain arrays (numpy) so the registration (:mod:`.register`) can treat a
fixed camera and a wrist camera alike. Observed points are kept as ``(du, dv, z)`` (pixel
offset from the principal point, depth) rather than as 3-D points, because the focal length
and the depth scale are unknowns of the fit: ``p = s * z * (du / f, dv / f, 1)``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from imac_data.errors import InputError

__all__ = ["RobotSurface", "camera_points", "lift", "static_background", "moving_pixels", "voxel_thin"]


def _sample_faces(vertices: np.ndarray, faces: np.ndarray, spacing: float, rng) -> tuple[np.ndarray, np.ndarray]:
    """Points about ``spacing`` apart on a triangle mesh, with the face normals."""
    tri = vertices[faces].astype(np.float64)  # (F, 3, 3)
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = 0.5 * np.linalg.norm(cross, axis=1)
    keep = area > 1e-12
    tri, cross, area = tri[keep], cross[keep], area[keep]
    if not len(tri):
        return np.zeros((0, 3)), np.zeros((0, 3))
    n = max(1, int(area.sum() / spacing**2))
    face = rng.choice(len(tri), size=n, p=area / area.sum())
    a, b = rng.random(n), rng.random(n)
    flip = a + b > 1
    a[flip], b[flip] = 1 - a[flip], 1 - b[flip]
    t = tri[face]
    pts = t[:, 0] + a[:, None] * (t[:, 1] - t[:, 0]) + b[:, None] * (t[:, 2] - t[:, 0])
    normals = cross[face] / np.linalg.norm(cross[face], axis=1, keepdims=True)
    return pts, normals


class RobotSurface:
    """Samples of the robot's visual surface with normals, per link, posed by forward kinematics.

    ``spacing``: about how far apart the samples are (metres). Normals matter more than
    density: the fit is point-to-plane, so a sparse sample of a flat face does not bias it.
    """

    def __init__(self, robot, spacing: float = 0.004, seed: int = 0):
        rng = np.random.default_rng(seed)
        pts, nrm, link = [], [], []
        self.links = sorted({m.link for m in robot.visual_meshes})
        index = {name: i for i, name in enumerate(self.links)}
        for mesh in robot.visual_meshes:
            p, n = _sample_faces(mesh.vertices, mesh.faces, spacing, rng)
            pts.append(p)
            nrm.append(n)
            link.append(np.full(len(p), index[mesh.link]))
        self.robot = robot
        self.points, self.normals, self.link = np.concatenate(pts), np.concatenate(nrm), np.concatenate(link)
        if not len(self.points):
            raise InputError(f"robot {robot.name!r}: its visual meshes have no surface to register to")

    def link_poses(self, q: np.ndarray) -> np.ndarray:
        """``(N, L, 4, 4)`` world poses of :attr:`links` for joint vectors ``q`` ``(N, D)``."""
        poses = self.robot.link_poses(torch.as_tensor(np.asarray(q, dtype=np.float64)))
        return np.stack([poses[name].numpy() for name in self.links], axis=1)

    def moving_links(self, q: np.ndarray, min_motion: float = 0.02) -> np.ndarray:
        """Indices of the links whose origin moves more than ``min_motion`` metres over ``q``:
        the ones a fixed camera's depth can tell from the static scene."""
        origin = self.link_poses(q)[..., :3, 3]  # (N, L, 3)
        spread = np.linalg.norm(origin - origin.mean(axis=0), axis=-1).max(axis=0)
        return np.flatnonzero(spread > min_motion)

    def posed(self, q: np.ndarray, links: Sequence[int] | None = None) -> list[tuple[np.ndarray, np.ndarray]]:
        """Per joint vector in ``q``: the world points and normals of ``links`` (default all)."""
        T = self.link_poses(q)
        sel = np.ones(len(self.points), bool) if links is None else np.isin(self.link, np.asarray(links))
        p, n, lk = self.points[sel], self.normals[sel], self.link[sel]
        out = []
        for Tk in T:
            R, t = Tk[lk, :3, :3], Tk[lk, :3, 3]
            out.append((np.einsum("nij,nj->ni", R, p) + t, np.einsum("nij,nj->ni", R, n)))
        return out


def camera_points(depth: np.ndarray, mask: np.ndarray, principal: tuple[float, float]) -> np.ndarray:
    """``(M, 3)`` rows ``(du, dv, z)`` of the pixels in ``mask`` with valid depth: the offset
    from the principal point ``(cx, cy)`` and the depth (metres)."""
    v, u = np.nonzero(mask & (depth > 0) & np.isfinite(depth))
    return np.stack([u - principal[0], v - principal[1], depth[v, u]], axis=1).astype(np.float64)


def lift(obs: np.ndarray, focal: float, scale: float = 1.0) -> np.ndarray:
    """Camera-frame points (OpenCV axes) of ``(du, dv, z)`` rows for a focal length (px) and depth scale."""
    z = obs[:, 2] * scale
    return np.stack([obs[:, 0] * z / focal, obs[:, 1] * z / focal, z], axis=1)


def static_background(depth: np.ndarray, quantile: float = 0.9) -> np.ndarray:
    """Per pixel, a high quantile of the valid depths over frames ``(N, H, W)``: what a fixed
    camera sees behind the moving arm (the arm only ever comes closer). 0 where no frame has depth."""
    valid = np.isfinite(depth) & (depth > 0)
    d = np.sort(np.where(valid, depth, np.inf).astype(np.float32), axis=0)  # invalid last
    n = valid.sum(axis=0)
    k = np.clip(np.floor(quantile * (n - 1)).astype(np.int64), 0, None)  # nanquantile, lower, 10x faster
    bg = np.take_along_axis(d, k[None], axis=0)[0]
    return np.where(n > 0, bg, 0.0).astype(np.float32)


def moving_pixels(depth: np.ndarray, background: np.ndarray, margin: float) -> np.ndarray:
    """``(N, H, W)`` bool: pixels nearer than the static background by more than ``margin``
    (metres, relative to depth: ``margin * background``) and the pixels with valid depth where the
    background has none. The robot's pixels in a fixed camera, found from depth alone."""
    valid = (depth > 0) & np.isfinite(depth)
    return valid & ((background <= 0) | (depth < background * (1.0 - margin)))


def voxel_thin(points: np.ndarray, size: float) -> np.ndarray:
    """Indices of one point per ``size`` voxel (the first), so dense near pixels do not dominate."""
    if not len(points):
        return np.zeros(0, np.int64)
    key = np.floor(points / size).astype(np.int64)
    _, first = np.unique(key, axis=0, return_index=True)
    return np.sort(first)
