"""Finding the red cube in an observation: red pixels, lifted to the world with their depth and
the camera's pose. Small functions over tensors; the policies and the judge share them."""

from __future__ import annotations

import torch

from imac_data.core.cameras import backproject

RED_THRESHOLD = 0.15  # redness r - max(g, b) of a cube pixel; the table, robot and shadows stay below 0.05


def redness(rgb: torch.Tensor) -> torch.Tensor:
    """``(..., 3, h, w)`` in [0, 1] -> ``(..., h, w)``: how much red exceeds the other channels."""
    return rgb[..., 0, :, :] - torch.maximum(rgb[..., 1, :, :], rgb[..., 2, :, :])


def interior(mask: torch.Tensor) -> torch.Tensor:
    """``mask`` without its edge pixels (those with a 4-neighbour outside it): at an object's
    edge a resized pixel mixes its colour with the depth of whatever lies in front or behind."""
    m = mask.clone()
    m[1:] &= mask[:-1]
    m[:-1] &= mask[1:]
    m[:, 1:] &= mask[:, :-1]
    m[:, :-1] &= mask[:, 1:]
    return m


def without_cube(rgb: torch.Tensor, threshold: float = 0.05) -> torch.Tensor:
    """``(..., 3, h, w)`` with the cube painted out: every reddish pixel (its antialiased edge
    included, grown by one pixel) takes the median colour of the frame's other pixels. What a
    judge reads from what is left, it reads from the arm and the table, not the cube."""
    red = redness(rgb.float()) > threshold
    grown = red.clone()
    grown[..., 1:, :] |= red[..., :-1, :]
    grown[..., :-1, :] |= red[..., 1:, :]
    grown[..., :, 1:] |= red[..., :, :-1]
    grown[..., :, :-1] |= red[..., :, 1:]
    h, w = rgb.shape[-2:]
    pixels = rgb.movedim(-3, -1).reshape(-1, h * w, 3).clone()  # (frames, pixels, rgb)
    for frame, m in zip(pixels, grown.reshape(-1, h * w)):
        if m.any() and (~m).any():
            frame[m] = frame[~m].median(dim=0).values
    return pixels.reshape(*rgb.shape[:-3], h, w, 3).movedim(-1, -3)


def red_points(rgb: torch.Tensor, depth: torch.Tensor, K: torch.Tensor, T_world_cam: torch.Tensor,
               threshold: float = RED_THRESHOLD, *, edges: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """World points ``(N, 3)`` of the red pixels with known depth, and their redness ``(N,)``;
    without ``edges``, of the red region's :func:`interior` only."""
    r = redness(rgb.float())
    red = r > threshold
    keep = (red if edges else interior(red)) & (depth > 0)
    points = backproject(depth.float(), K.float(), T_world_cam.float())
    return points[keep], r[keep]


def cube_centre_xy(points: torch.Tensor, weights: torch.Tensor, min_points: int = 1) -> torch.Tensor | None:
    """The cube's centre in the table plane: the redness-weighted mean of its red points
    (None with fewer than ``min_points``). The visible faces pull it towards the camera by
    less than a centimetre at these view sizes (docs/ranking.md)."""
    if len(points) < max(1, min_points):
        return None
    w = weights.clamp_min(1e-6)
    return (points[:, :2] * w[:, None]).sum(0) / w.sum()
