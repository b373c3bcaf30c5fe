"""The reference scene seen from where the cameras will be: a forward warp of the reference frame.

A wrist camera moves with the arm, so in a chunk's future frames the scene it saw at the
reference lands somewhere else in its image, and a view that did not see the object at the
reference may see it later. The warp places it by geometry: every view's reference RGB-D,
robot removed and cropped to the workspace (:func:`~imac_data.core.contact.clouds.scene_cloud`),
splatted with a z-buffer into each view's camera at each future configuration. It is an added
control stream beyond the paper's (``docs/world-model.md``, "The scene-warp stream").

Plain torch over tensors, with the contact streams' conventions: pixel centres at integer
coordinates, OpenCV camera axes, camera-to-world poses, metres.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from imac_data.core.cameras import project
from imac_data.errors import InputError

__all__ = ["splat", "DEFAULT_FILL", "SAME_SURFACE"]

SAME_SURFACE = 0.02  # depth share within which a view's own point beats another view's (one surface)
DEFAULT_FILL = 1  # hole-filling passes; more grow the objects nearest the camera (measured: docs/world-model.md)


def splat(points: torch.Tensor, colours: torch.Tensor, K: torch.Tensor, T_world_cam: torch.Tensor,
          hw: tuple[int, int], *, source_view: torch.Tensor | None = None, fill: int = DEFAULT_FILL,
          ) -> tuple[torch.Tensor, torch.Tensor]:
    """Z-buffered splat of world ``points (P, 3)`` with ``colours (P, C)`` into the cameras
    ``K (V, 3, 3)`` at poses ``T_world_cam (N, V, 4, 4)`` of images ``hw = (H, W)``: returns
    ``(images (N, V, H, W, C), depth (N, V, H, W))``, in the colours' dtype and metres, 0 where no
    point lands. Each point takes its nearest pixel; the point nearest the camera wins (ties: the
    highest index). ``source_view (P,)``: the view each point was seen in; a view's own points then
    win over others' within :data:`SAME_SURFACE` of their depth (one surface seen twice: the view's
    own pixel is its own colour, exactly where it was). Then ``fill`` passes give each empty pixel its front-most neighbour of the
    3x3 around it."""
    points = torch.as_tensor(points, dtype=torch.float32)
    colours = torch.as_tensor(colours)
    K = torch.as_tensor(K, dtype=torch.float32)
    T = torch.as_tensor(T_world_cam, dtype=torch.float32)
    if points.ndim != 2 or points.shape[1] != 3:
        raise InputError(f"scene warp: points must be (P, 3), got {tuple(points.shape)}")
    if colours.ndim != 2 or colours.shape[0] != points.shape[0]:
        raise InputError(f"scene warp: colours must be (P={points.shape[0]}, C), got {tuple(colours.shape)}")
    if T.ndim != 4 or T.shape[-2:] != (4, 4) or K.shape != (T.shape[1], 3, 3):
        raise InputError(f"scene warp: poses must be (N, V, 4, 4) and K (V, 3, 3), got {tuple(T.shape)} and "
                         f"{tuple(K.shape)}")
    if int(fill) < 0:
        raise InputError(f"scene warp: fill must be >= 0 passes, got {fill}")
    N, V = T.shape[:2]
    H, W = (int(x) for x in hw)
    n_img, P, C = N * V, points.shape[0], colours.shape[1]
    z_img = torch.zeros(n_img, H * W)
    idx_img = torch.full((n_img, H * W), -1, dtype=torch.long)
    if P:
        uv, z = project(points.expand(n_img, P, 3), K.repeat(N, 1, 1), T.reshape(n_img, 4, 4))
        u, v = uv[..., 0].round(), uv[..., 1].round()
        ok = (z > 1e-6) & torch.isfinite(uv).all(-1) & (u >= 0) & (u < W) & (v >= 0) & (v < H)
        image, point = torch.nonzero(ok, as_tuple=True)
        key = image * (H * W) + (v[ok] * W + u[ok]).long()
        zk = z[ok]
        if source_view is not None:  # depth as the z-test sees it: other views' points a little farther
            own = torch.as_tensor(source_view, dtype=torch.long)[point] == image % V
            zk = torch.where(own, zk, zk * (1.0 + SAME_SURFACE))
        zbuf = torch.full((n_img * H * W,), float("inf")).scatter_reduce(0, key, zk, "amin")
        front = zk == zbuf[key]
        winner = torch.full((n_img * H * W,), -1, dtype=torch.long).scatter_reduce(0, key[front], point[front], "amax")
        idx_img = winner.reshape(n_img, H * W)
        z_img = torch.where(idx_img >= 0, z.reshape(-1)[(torch.arange(n_img)[:, None] * P + idx_img.clamp_min(0))]
                            if P else zbuf.reshape(n_img, H * W), torch.zeros(()))
    idx_img, z_img = idx_img.reshape(n_img, 1, H, W), z_img.reshape(n_img, 1, H, W)
    for _ in range(int(fill)):
        empty = idx_img < 0
        if not empty.any():
            break
        far = torch.where(empty, torch.full_like(z_img, float("inf")), z_img)
        near = F.unfold(F.pad(far, (1, 1, 1, 1), value=float("inf")), 3).reshape(n_img, 9, H, W)
        neighbour = F.unfold(F.pad(idx_img.float(), (1, 1, 1, 1), value=-1.0), 3).reshape(n_img, 9, H, W).long()
        best = near.argmin(dim=1, keepdim=True)
        found = torch.isfinite(near.gather(1, best)) & empty
        idx_img = torch.where(found, neighbour.gather(1, best), idx_img)
        z_img = torch.where(found, near.gather(1, best), z_img)
    hit = idx_img >= 0
    images = torch.zeros(n_img, H, W, C, dtype=colours.dtype)
    images[hit[:, 0]] = colours[idx_img[hit]]
    return images.reshape(N, V, H, W, C), z_img.reshape(N, V, H, W)
