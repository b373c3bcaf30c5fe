"""The six-panel mosaic, the resize and the intrinsics that follow it."""

import numpy as np
import pytest
import torch

from imac_data.core.cameras import project
from imac_data.errors import InputError
from imac_model.data import mosaic


def test_mosaic_layout_and_inverse():
    B, T, V, h, w = 2, 3, 3, 4, 5
    rgb = torch.rand(B, T, V, 3, h, w)
    depth = torch.rand(B, T, V, 3, h, w)
    m = mosaic.assemble(rgb, depth)
    assert m.shape == (B, T, 3, 2 * h, V * w)
    for v in range(V):  # RGB row over depth row, views left to right
        assert torch.equal(m[..., :h, v * w:(v + 1) * w], rgb[:, :, v])
        assert torch.equal(m[..., h:, v * w:(v + 1) * w], depth[:, :, v])
    r, d = mosaic.split(m, V)
    assert torch.equal(r, rgb) and torch.equal(d, depth)
    c = mosaic.controls(rgb)
    assert torch.equal(c[..., :h, :], c[..., h:, :]) and torch.equal(c[..., :h, :], m[..., :h, :])
    assert torch.equal(mosaic.control_views(c, V), rgb)


def test_view_size_keeps_aspect_and_patchifies():
    assert mosaic.view_size((240, 320), 48, multiple=8, num_views=3) == (48, 64)
    h, w = mosaic.view_size((480, 640), 224, multiple=32, num_views=3)  # Wan2.2: multiples of 32
    assert (2 * h) % 32 == 0 and (3 * w) % 32 == 0 and abs(w / h - 4 / 3) < 0.05
    with pytest.raises(InputError, match=r"data.view_height: 40 cannot be patchified.*use 32 or 48"):
        mosaic.view_size((240, 320), 40, multiple=32, num_views=3)
    with pytest.raises(InputError, match="data.view_width"):
        mosaic.view_size((240, 320), 48, 48, multiple=8, num_views=3)  # 1:1 from 3:4


def test_depth_resize_only_returns_measured_colours():
    codes = torch.randint(0, 256, (1, 3, 12, 16)).float() / 255
    small = mosaic.resize_frames(codes, (6, 8), kind="depth")
    colours = set(map(tuple, codes[0].flatten(1).T.tolist()))
    assert all(tuple(c) in colours for c in small[0].flatten(1).T.tolist())


def test_rescaled_K_follows_the_resized_image():
    """A blob drawn where K projects a 3D point: after the antialiased resize its centroid
    must be where the rescaled K projects the same point (oracle: the image itself)."""
    H, W, h, w = 480, 640, 48, 64
    K = np.array([[500.0, 0, 319.5], [0, 500.0, 239.5], [0, 0, 1]])
    T = torch.eye(4)
    point = torch.tensor([[0.031, -0.017, 1.0]])
    uv = project(point, torch.tensor(K, dtype=torch.float32), T)[0][0]
    yy, xx = torch.meshgrid(torch.arange(H, dtype=torch.float32), torch.arange(W, dtype=torch.float32), indexing="ij")
    blob = torch.exp(-((xx - uv[0]) ** 2 + (yy - uv[1]) ** 2) / (2 * 15.0 ** 2))
    small = mosaic.resize_frames(blob.expand(3, H, W), (h, w))[0]
    sy, sx = torch.meshgrid(torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32), indexing="ij")
    centroid = torch.stack([(small * sx).sum(), (small * sy).sum()]) / small.sum()
    K_small = mosaic.rescale_K(K, (H, W), (h, w))
    uv_small = project(point, torch.tensor(K_small, dtype=torch.float32), T)[0][0]
    assert torch.allclose(centroid, uv_small, atol=0.03), (centroid, uv_small)
    naive = K[:2, 2] * np.array([w / W, h / H])  # scaling the principal point alone is half a pixel off
    assert abs(naive[0] - K_small[0, 2]) > 0.4


@pytest.mark.parametrize("width", [64, 128, 400])
def test_sample_labels_fit_their_panel(width):
    """A label is drawn whole inside its panel however narrow (a one-camera mosaic): the font
    shrinks first, and only below a legible size is the text cut (ending in '~')."""
    from imac_model.evaluate.pictures import label

    blank = np.full((96, width, 3), 128, np.uint8)
    for text in ("generated t+1", "a much longer label than any panel of this width can hold"):
        drawn = np.any(label(blank.copy(), text) != 128, axis=(0, 2))
        cols = np.flatnonzero(drawn)
        assert len(cols) and cols.max() < width - 2, (text, width, cols.max())  # not clipped by the edge
    # shrunk rather than cut short: on a 64-pixel panel the short label still spans most of the width
    narrow = np.flatnonzero(np.any(label(np.full((96, 64, 3), 128, np.uint8), "generated t+1") != 128, axis=(0, 2)))
    assert narrow.max() - narrow.min() > 40
