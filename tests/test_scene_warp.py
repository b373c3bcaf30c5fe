"""The scene warp (imac_data.core.scene_warp, Rig.scene_warp, the model's derived stream) against
analytic geometry: a plane seen by one camera and warped into another lands where the other
camera's rays meet the plane; the nearer of two surfaces wins; and the stream the training data
derives is the one a rollout rebuilds."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from imac_data.core.cameras import backproject, intrinsics_from_fovy, look_at, pixel_rays
from imac_data.core.scene_warp import splat
from imac_data.errors import InputError

H, W = 48, 64
K = torch.as_tensor(intrinsics_from_fovy(50.0, W, H), dtype=torch.float32)


def plane_depth(T_world_cam: torch.Tensor) -> torch.Tensor:
    """Analytic z-depth (H, W) of the plane z = 0 seen from ``T_world_cam`` (0 where a ray misses it)."""
    rays = pixel_rays(K, H, W) @ T_world_cam[:3, :3].T  # world directions, camera z = 1
    t = -T_world_cam[2, 3] / rays[:, 2]
    return torch.where(t > 0, t, torch.zeros(())).reshape(H, W)


def plane_hits(T_world_cam: torch.Tensor) -> torch.Tensor:
    """World (x, y) where each pixel's ray meets the plane z = 0, (H, W, 2)."""
    return backproject(plane_depth(T_world_cam), K, T_world_cam)[..., :2]


def pose(eye, target=(0.0, 0.0, 0.0)) -> torch.Tensor:
    return torch.as_tensor(look_at(eye, target, up=(0.0, 1.0, 0.0)), dtype=torch.float32)


def test_a_plane_warped_into_a_closer_camera_lands_where_its_rays_meet_the_plane():
    """Each point carries its own world (x, y) as its colour: the warp's colour at a target pixel is
    then the point that landed there, and the analytic oracle is where that pixel's ray meets the
    plane. A camera 1.6x closer, seen from the side, spreads the points: one fill pass closes it."""
    source, target = pose((0.0, 0.0, 1.0)), pose((0.12, -0.08, 0.6), (0.03, 0.02, 0.0))
    depth = plane_depth(source)
    points = backproject(depth, K, source).reshape(-1, 3)
    colours = points[:, :2].clone()
    truth = plane_hits(target)
    inside = (truth.abs() < 0.9 * truth.new_tensor([plane_hits(source)[..., 0].max(), plane_hits(source)[..., 1].max()])).all(-1)
    footprint = float(depth.mean() / K[0, 0])  # metres between the source's samples
    # without filling, the closer camera's pixels outnumber the points by about 1.6^2: 39 % are hit
    for fill, (least, most), worst in ((0, (0.30, 0.50), 0.75), (1, (0.99, 1.0), 2.0)):
        images, zbuf = splat(points, colours, K[None], target[None, None], (H, W), fill=fill)
        hit = zbuf[0, 0] > 0
        share = float((hit & inside).sum() / inside.sum())
        assert least <= share <= most, (fill, share)
        error = (images[0, 0] - truth).norm(dim=-1)[hit & inside] / footprint
        # a point lands on its nearest pixel (half a target pixel off at most, 0.3 source samples) and a filled
        # pixel takes its neighbour's: within about one source sample of the truth
        assert float(error.median()) < 0.75 and float(error.max()) < worst, (fill, error.median(), error.max())
        expected_z = plane_depth(target)
        assert torch.allclose(zbuf[0, 0][hit & inside], expected_z[hit & inside], rtol=0.05)


def test_the_nearest_surface_wins_and_the_same_pose_gives_the_frame_back():
    """A square 0.3 m above the plane hides the plane behind it in a moved camera, whatever order
    the points come in; warped into its own camera the frame comes back pixel for pixel."""
    source = pose((0.0, 0.0, 1.0))
    plane = backproject(plane_depth(source), K, source).reshape(-1, 3)
    xs = torch.linspace(-0.05, 0.05, 30)
    square = torch.stack(torch.meshgrid(xs, xs, indexing="ij") + (torch.full((30, 30), 0.3),), -1).reshape(-1, 3)
    tags = torch.cat([torch.zeros(len(plane)), torch.ones(len(square))])[:, None]
    target = pose((0.2, 0.0, 0.9), (0.0, 0.0, 0.0))
    seen = []
    for order in (torch.arange(len(tags)), torch.randperm(len(tags), generator=torch.Generator().manual_seed(0))):
        images, zbuf = splat(torch.cat([plane, square])[order], tags[order], K[None], target[None, None], (H, W),
                             fill=0)
        seen.append(images[0, 0, :, :, 0])
        on_square = images[0, 0, :, :, 0] == 1
        assert on_square.sum() > 50
        assert float(zbuf[0, 0][on_square].max()) < 0.85  # the square's depth, not the plane's (~0.9-1.1)
    assert torch.equal(seen[0], seen[1])
    colours = torch.arange(H * W, dtype=torch.float32)[:, None]
    same, _ = splat(plane, colours, K[None], source[None, None], (H, W), fill=0)
    assert torch.equal(same[0, 0, :, :, 0].flatten(), colours[:, 0])


def test_bad_shapes_name_what_is_wrong():
    with pytest.raises(InputError, match="points must be"):
        splat(torch.zeros(5, 2), torch.zeros(5, 3), K[None], torch.eye(4)[None, None], (H, W))
    with pytest.raises(InputError, match="colours must be"):
        splat(torch.zeros(5, 3), torch.zeros(4, 3), K[None], torch.eye(4)[None, None], (H, W))
    with pytest.raises(InputError, match="poses must be"):
        splat(torch.zeros(5, 3), torch.zeros(5, 3), K[None], torch.eye(4)[None], (H, W))
    empty, zbuf = splat(torch.zeros(0, 3), torch.zeros(0, 3, dtype=torch.uint8), K[None], torch.eye(4)[None, None],
                        (H, W))
    assert empty.shape == (1, 1, H, W, 3) and not empty.any() and not zbuf.any()
    assert np.isfinite(zbuf.numpy()).all()
