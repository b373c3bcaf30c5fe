"""Registration of depth to a known world, with no starting pose: global candidates from
FPFH features and RANSAC (open3d), then one robust point-to-plane fit over all frames at once.

The model of a frame ``i``: a world point ``w = A_i @ X @ p``, where ``p`` is the observed
camera point ``s * z * (du / f, dv / f, 1)``, ``A_i`` is known (identity for a fixed camera, the
link's forward-kinematics pose for a wrist camera) and ``X`` is the unknown camera pose
(``T_world_cam``, or the mount ``T_link_cam``). The fit solves for ``X`` and, where they are
unknown, the focal length ``f`` and the depth scale ``s``, by Gauss-Newton on the distance of
``w`` to the tangent plane of its nearest target point, with Tukey weights so that points with
no counterpart (the cube, a clipped finger, a wall) stop pulling.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from imac_data.calibrate.surface import lift
from imac_data.core.kdtree import kdtree

__all__ = ["Target", "Fit", "fpfh_candidates", "fit_pose", "evaluate_pose", "score_pose", "se3_exp"]


@dataclass
class Target:
    """What the frame's observed points must land on (world frame): points, unit normals, and their exact
    KD-tree (pykdtree: 3x faster than scipy's to build and to query here; docs/calibration.md, "Accuracy and
    time")."""

    points: np.ndarray
    normals: np.ndarray
    tree: object = None

    def __post_init__(self) -> None:
        if self.tree is None:
            self.tree = kdtree(self.points)


@dataclass
class Fit:
    """The result of :func:`fit_pose`: pose, focal (px), depth scale, and how well it fits."""

    X: np.ndarray
    focal: float
    scale: float
    inlier_ratio: float  # observed points within the final inlier distance of the target
    residual_mm: float  # RMS point-to-plane distance of the inliers
    iterations: int


def se3_exp(xi: np.ndarray) -> np.ndarray:
    """4x4 transform of a twist ``(v, w)`` (small-step update; Rodrigues for the rotation)."""
    v, w = xi[:3], xi[3:]
    th = np.linalg.norm(w)
    W = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    if th < 1e-12:
        R = np.eye(3) + W
    else:
        R = np.eye(3) + np.sin(th) / th * W + (1 - np.cos(th)) / th**2 * W @ W
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, v
    return T


def _pcd(points: np.ndarray, voxel: float):
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, dtype=np.float64)))
    pcd = pcd.voxel_down_sample(voxel)
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=2.5 * voxel, max_nn=30))
    feat = o3d.pipelines.registration.compute_fpfh_feature(
        pcd, o3d.geometry.KDTreeSearchParamHybrid(radius=5.0 * voxel, max_nn=100))
    return pcd, feat


def fpfh_candidates(source: np.ndarray, target: np.ndarray, voxel: float, *, with_scaling: bool = False,
                    runs: int = 4, seed: int = 0, iterations: int = 200_000) -> list[np.ndarray]:
    """Similarity transforms source -> target from ``runs`` RANSAC runs on FPFH matches at
    ``voxel`` metres (open3d's ``registration_ransac_based_on_feature_matching``). Several runs,
    because one run on a partial, repetitive robot surface can lock onto a wrong match; the
    caller scores every candidate on the whole problem."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    src, fs = _pcd(source, voxel)
    dst, fd = _pcd(target, voxel)
    out = []
    for k in range(runs):
        o3d.utility.random.seed(seed + k)
        # half the runs with the mutual filter; its "too few correspondences" fallback is expected, not news
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
            res = reg.registration_ransac_based_on_feature_matching(
                src, dst, fs, fd, bool(k % 2), 1.5 * voxel,
                reg.TransformationEstimationPointToPoint(with_scaling), 3,
                [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9),
                 reg.CorrespondenceCheckerBasedOnDistance(1.5 * voxel)],
                reg.RANSACConvergenceCriteria(iterations, 0.9999))
        T = np.asarray(res.transformation, dtype=np.float64)
        det = np.linalg.det(T[:3, :3]) if np.isfinite(T).all() else 0.0
        if res.fitness > 0 and 0.3 < det < 3.0:  # a scale beyond 0.67-1.44 is a degenerate sample, not a pose
            out.append(T)
    return out


def _weights(r: np.ndarray, c: float) -> np.ndarray:
    """Tukey's biweight: full weight near 0, none beyond ``c``."""
    u = np.clip(np.abs(r) / c, 0, 1)
    return (1 - u**2) ** 2


def score_pose(obs: Sequence[np.ndarray], A: np.ndarray, X: np.ndarray, targets: Sequence[Target], focal: float,
               scale: float, dist: float) -> float:
    """Fraction of observed points within ``dist`` metres of their target (a candidate's worth)."""
    hit = total = 0
    for o, Ai, tg in zip(obs, A, targets):
        M = Ai @ X
        w = lift(o, focal, scale) @ M[:3, :3].T + M[:3, 3]
        d, _ = tg.tree.query(w, distance_upper_bound=dist)
        hit += int(np.isfinite(d).sum())
        total += len(o)
    return hit / max(total, 1)


def fit_pose(obs: Sequence[np.ndarray], A: np.ndarray, X0: np.ndarray, targets: Sequence[Target], focal0: float, *,
             scale0: float = 1.0, free_focal: bool = False, free_scale: bool = False,
             schedule: Sequence[float] = (0.05, 0.03, 0.02, 0.012, 0.008), iterations: int = 12,
             tol: float = 1e-6) -> Fit:
    """Robust joint fit of ``X`` (and focal, scale) over every frame: Gauss-Newton on
    point-to-plane residuals, Tukey weights whose cut-off walks down ``schedule`` (metres), so
    a start a few centimetres off still finds its correspondences and the end ignores outliers.

    ``obs[i]``: ``(M_i, 3)`` rows ``(du, dv, z)`` of frame i; ``A`` ``(N, 4, 4)``; ``X0`` 4x4."""
    X, lf, ls = np.array(X0, dtype=np.float64), np.log(focal0), np.log(scale0)
    free = [True] * 6 + [free_focal, free_scale]
    it = 0
    for cut in schedule:
        for _ in range(iterations):
            it += 1
            H, g = np.zeros((8, 8)), np.zeros(8)
            for o, Ai, tg in zip(obs, A, targets):
                if not len(o):
                    continue
                p = lift(o, np.exp(lf), np.exp(ls))
                M = Ai @ X
                w = p @ M[:3, :3].T + M[:3, 3]
                d, j = tg.tree.query(w, distance_upper_bound=2.0 * cut)
                ok = np.isfinite(d)
                if not ok.any():
                    continue
                p, w, j = p[ok], w[ok], j[ok]
                n = tg.normals[j]
                r = np.einsum("ij,ij->i", n, w - tg.points[j])
                wt = _weights(r, cut)
                nc = n @ M[:3, :3]  # the normal in camera axes
                J = np.concatenate([nc, np.cross(p, nc), -np.einsum("ij,ij->i", nc, p * [1, 1, 0])[:, None],
                                    np.einsum("ij,ij->i", nc, p)[:, None]], axis=1)
                H += (J * wt[:, None]).T @ J
                g += (J * wt[:, None]).T @ r
            idx = np.flatnonzero(free)
            Hs = H[np.ix_(idx, idx)] + 1e-9 * np.eye(len(idx)) * max(np.trace(H), 1.0)
            try:
                step = -np.linalg.solve(Hs, g[idx])
            except np.linalg.LinAlgError:
                break
            delta = np.zeros(8)
            delta[idx] = step
            X = X @ se3_exp(delta[:6])
            lf += delta[6]
            ls += delta[7]
            if np.abs(delta[:3]).max() < tol and np.abs(delta[3:]).max() < tol * 10:
                break
    ratio, rms = evaluate_pose(obs, A, X, targets, float(np.exp(lf)), float(np.exp(ls)), schedule[-1])
    return Fit(X, float(np.exp(lf)), float(np.exp(ls)), ratio, rms, it)


def evaluate_pose(obs: Sequence[np.ndarray], A: np.ndarray, X: np.ndarray, targets: Sequence[Target], focal: float,
                  scale: float, cut: float) -> tuple[float, float]:
    """(share of observed points within ``cut`` metres of the target, RMS point-to-plane mm of those)."""
    inl = tot = 0
    sq = 0.0
    for o, Ai, tg in zip(obs, A, targets):
        M = Ai @ X
        w = lift(o, focal, scale) @ M[:3, :3].T + M[:3, 3]
        d, j = tg.tree.query(w, distance_upper_bound=cut)
        ok = np.isfinite(d)
        r = np.einsum("ij,ij->i", tg.normals[j[ok]], w[ok] - tg.points[j[ok]])
        inl += int(ok.sum())
        tot += len(o)
        sq += float((r**2).sum())
    return inl / max(tot, 1), float(1e3 * np.sqrt(sq / max(inl, 1)))
