"""The depth colour codec (imac_data.core.depth) against independent oracles: the power
transform written out here from docs/dataset-format.md, a brute-force nearest point on a
densely sampled walk, and the analytic 8-bit quantisation step."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from imac_data.core.depth import (
    CORNERS,
    N_CODES,
    DepthCodec,
    path_position,
)
from imac_data.core.metric_depth import depth_from_millimetres
from imac_data.errors import InputError

PRESET_NAMES = ["manipulation", "general"]
DEVICES = [
    "cpu",
    pytest.param(
        "cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
    ),
]
RNG = np.random.default_rng(20260421)

# The walk, written out from docs/dataset-format.md: black, red, yellow, green, cyan, blue, magenta, white.
WALK = np.array(
    [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 1, 1], [0, 0, 1], [1, 0, 1], [1, 1, 1]], float
)


def oracle_f(d, lam, c):
    """f(d) = 1 - (1 - d/(lam c))^(lam+1), in float64."""
    return 1.0 - (1.0 - np.asarray(d, np.float64) / (lam * c)) ** (lam + 1.0)


def oracle_colour(s):
    """Colour at walk position s in [0, 7], by linear interpolation between corners."""
    s = np.asarray(s, np.float64)
    k = np.clip(np.floor(s).astype(int), 0, 6)
    t = (s - k)[..., None]
    return WALK[k] * (1 - t) + WALK[k + 1] * t


def sweep(codec: DepthCodec, lo=0.01, hi=20.0, n=20001):
    """Geometric depths in [lo, hi], capped just inside the codec's range."""
    return np.geomspace(lo, min(hi, 0.999 * codec.max_depth), n)


def rel_err(a, b):
    return np.max(np.abs(np.asarray(a, np.float64) / np.asarray(b, np.float64) - 1.0))


# ------------------------------------------------------------------------ parameters
def test_presets_and_defaults():
    assert DepthCodec() == DepthCodec.preset() == DepthCodec.preset("manipulation")
    assert DepthCodec.preset("manipulation") == DepthCodec(-500, 0.53)
    assert DepthCodec.preset("general") == DepthCodec(-3, 10 / 3)
    assert DepthCodec(-3, 10 / 3).preset_name == "general"
    assert DepthCodec(-4, 120).preset_name is None
    assert CORNERS.tolist() == WALK.tolist()


@pytest.mark.parametrize(
    "lam, c, field",
    [(-1.0, 1.0, "lam"), (-0.5, 1.0, "lam"), (2.0, 1.0, "lam"), (float("nan"), 1.0, "lam"),
     ("-3", 1.0, "lam"), (True, 1.0, "lam"), (-3.0, 0.0, "c"), (-3.0, -1.0, "c"),
     (-3.0, float("inf"), "c")],
)
def test_bad_parameters_raise(lam, c, field):
    with pytest.raises(InputError, match=rf"\b{field}\b"):
        DepthCodec(lam, c)


def test_unknown_preset_lists_known():
    with pytest.raises(InputError, match="general.*manipulation"):
        DepthCodec.preset("outdoor")


@pytest.mark.parametrize("codec", [DepthCodec.preset("manipulation"), DepthCodec.preset("general"),
                                   DepthCodec(-4.0, 120.0)])
def test_metadata_round_trip_through_json(codec):
    meta = json.loads(json.dumps(codec.to_dict()))
    assert DepthCodec.from_dict(meta) == codec
    assert meta["preset"] == codec.preset_name


def test_bad_metadata_raises():
    good = DepthCodec().to_dict()
    with pytest.raises(InputError, match="codec"):
        DepthCodec.from_dict({**good, "codec": "turbo"})
    with pytest.raises(InputError, match="missing.*'c'"):
        DepthCodec.from_dict({k: v for k, v in good.items() if k != "c"})
    with pytest.raises(InputError, match="path"):
        DepthCodec.from_dict({**good, "path": good["path"][::-1]})
    with pytest.raises(InputError, match="lam"):
        DepthCodec.from_dict({**good, "lam": -0.5})


# ------------------------------------------------------------------- the definition
@pytest.mark.parametrize("preset", PRESET_NAMES)
def test_encode_follows_the_definition(preset):
    codec = DepthCodec.preset(preset)
    d = sweep(codec, n=2001)
    expected = oracle_colour(7.0 * oracle_f(d, codec.lam, codec.c))
    np.testing.assert_allclose(codec.encode(d), expected, atol=1e-9)
    np.testing.assert_allclose(codec.encode(d.astype(np.float32)), expected, atol=2e-6)


@pytest.mark.parametrize("preset", PRESET_NAMES)
def test_range_and_quantisation_step_match_the_definition(preset):
    codec = DepthCodec.preset(preset)
    lam, c = codec.lam, codec.c
    # min/max depth are the depths at codes 1 and 1784.
    assert oracle_f(codec.min_depth, lam, c) * N_CODES == pytest.approx(1.0, rel=1e-9)
    assert oracle_f(codec.max_depth, lam, c) * N_CODES == pytest.approx(N_CODES - 1, rel=1e-12)
    # quantisation step = 1 / (1785 f'(d)), f' by central differences.
    d = np.array([0.05, 0.1, 0.5, 1.0, 2.0])
    h = 1e-6
    slope = (oracle_f(d + h, lam, c) - oracle_f(d - h, lam, c)) / (2 * h)
    np.testing.assert_allclose(codec.quantisation_step(d), 1.0 / (N_CODES * slope), rtol=1e-5)


def test_manipulation_steps_quoted_in_design_md():
    # docs/dataset-format.md: 0.4 mm at 0.1 m, 2 mm at 1 m, 2.8 mm at 1.2 m, 13 mm at 2 m.
    steps = DepthCodec.preset("manipulation").quantisation_step([0.1, 1.0, 1.2, 2.0])
    np.testing.assert_allclose(steps, [0.4e-3, 2e-3, 2.8e-3, 13e-3], rtol=0.11)


# ------------------------------------------------------------------------ round trips
@pytest.mark.parametrize("preset", PRESET_NAMES)
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_float_round_trip_numpy(preset, dtype):
    codec = DepthCodec.preset(preset)
    d = sweep(codec).astype(dtype)
    rgb = codec.encode(d)
    assert rgb.shape == d.shape + (3,) and rgb.dtype == dtype
    assert rgb.min() >= 0.0 and rgb.max() <= 1.0
    back = codec.decode(rgb)
    assert back.shape == d.shape and back.dtype == dtype
    assert rel_err(back, d) < 1e-5


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("preset", PRESET_NAMES)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_float_round_trip_torch(preset, dtype, device):
    codec = DepthCodec.preset(preset)
    d = torch.as_tensor(sweep(codec), dtype=dtype, device=device).reshape(1, -1, 1)
    rgb = codec.encode(d)
    assert rgb.shape == (1, d.shape[1], 1, 3) and rgb.dtype == dtype and rgb.device == d.device
    back = codec.decode(rgb)
    assert back.shape == d.shape and back.dtype == dtype and back.device == d.device
    assert rel_err(back.cpu().numpy(), d.cpu().numpy()) < 1e-5
    # Same frames as numpy (rounding ties may differ by one LSB).
    frames = codec.encode_uint8(d).cpu().numpy()
    ref = codec.encode_uint8(d.cpu().numpy())
    assert frames.dtype == np.uint8 and np.abs(frames.astype(int) - ref).max() <= 1
    assert (frames != ref).any(axis=-1).mean() < 1e-3


@pytest.mark.parametrize("preset", PRESET_NAMES)
def test_uint8_round_trip_within_half_a_code(preset):
    codec = DepthCodec.preset(preset)
    d = sweep(codec, lo=0.005, n=200001).astype(np.float32)
    frames = codec.encode_uint8(d)
    assert frames.dtype == np.uint8 and frames.shape == d.shape + (3,)
    back = codec.decode(frames)
    # The step grows with depth, so half the step at the larger depth bounds the error.
    bound = 0.5 * codec.quantisation_step(np.maximum(back, d))
    assert np.all(np.abs(back - d) <= bound * (1 + 1e-4) + 1e-7 * d)
    # ... and the decoded depths are exactly the code depths.
    codes = np.rint(path_position(frames) * 255).astype(int)
    np.testing.assert_allclose(back, codec.depth_of_code(codes), rtol=2e-6)


def test_out_of_range_depth_saturates():
    codec = DepthCodec.preset("manipulation")
    far = np.array([5.0, 20.0, 1e6], np.float32)
    frames = codec.encode_uint8(far)
    assert (frames == [255, 254, 255]).all()  # code 1784, the last before white
    np.testing.assert_allclose(codec.decode(frames), codec.max_depth, rtol=1e-6)
    np.testing.assert_allclose(codec.decode(codec.encode(far)), codec.max_depth, rtol=1e-6)
    assert codec.decode(np.array([255, 255, 255], np.uint8)) == pytest.approx(codec.max_depth, rel=1e-6)
    near = np.array([1e-9, 1e-5], np.float32)  # below code 1: clamped up, never black
    assert (codec.encode_uint8(near) == [1, 0, 0]).all()
    np.testing.assert_allclose(codec.decode(codec.encode_uint8(near)), codec.min_depth, rtol=1e-5)


@pytest.mark.parametrize("preset", PRESET_NAMES)
def test_millimetre_depth_colours_equal_the_computed_ones(preset):
    """float32 depth from whole millimetres is looked up in a table: the colours must be
    the ones computed value by value (one-element arrays take numpy's scalar/tail loops,
    the table was filled by its vector loops), on and off the millimetre grid."""
    codec = DepthCodec.preset(preset)
    grid = depth_from_millimetres(np.arange(1 << 16, dtype=np.uint16))
    looked_up = codec.encode_uint8(grid.reshape(256, 256)).reshape(-1, 3)
    # every entry against the computed colours of a reversed (non-contiguous) view
    np.testing.assert_array_equal(looked_up[::-1], codec._encode_uint8_computed(grid[::-1]))
    pick = RNG.choice(len(grid), 2000, replace=False)
    one_by_one = np.stack([codec._encode_uint8_computed(grid[i:i + 1])[0] for i in pick])
    np.testing.assert_array_equal(looked_up[pick], one_by_one)

    # A frame mixing grid values with off-grid, invalid and out-of-table values.
    values = np.concatenate([grid[pick[:500]], grid[pick[500:900]] + np.float32(1.7e-4),
                             np.float32([0.0, -0.0, np.nan, np.inf, -np.inf, 65.535, 65.536, 70.0, 1e-7])])
    values = RNG.permutation(values).astype(np.float32)
    got = codec.encode_uint8(values[:900].reshape(2, 18, 25))
    want = np.stack([codec._encode_uint8_computed(values[i:i + 1])[0] for i in range(900)])
    np.testing.assert_array_equal(got.reshape(-1, 3), want)
    np.testing.assert_array_equal(codec.encode_uint8(values[:900].reshape(18, 50), channel_axis=0),
                                  np.moveaxis(want.reshape(18, 50, 3), -1, 0))

    # The table against the analytic oracle: min_depth .. max_depth decode within half a code step.
    mm = np.arange(int(codec.min_depth * 1000) + 1, min(len(grid), int(codec.max_depth * 1000)))
    back = codec.decode(looked_up[mm])
    bound = 0.5 * codec.quantisation_step(np.maximum(back, grid[mm]))
    assert np.all(np.abs(back - grid[mm]) <= bound * (1 + 1e-4) + 1e-7 * grid[mm])


# ---------------------------------------------------------------------------- invalid
@pytest.mark.parametrize("backend", ["numpy", "torch"])
def test_invalid_depth_is_black_and_decodes_invalid(backend):
    codec = DepthCodec()
    d = np.array([[0.0, np.nan, np.inf, -np.inf, -0.0, 0.7]], np.float32)
    x = torch.from_numpy(d) if backend == "torch" else d
    rgb, frames = codec.encode(x), codec.encode_uint8(x)
    rgb, frames = np.asarray(rgb), np.asarray(frames)
    assert (rgb[0, :5] == 0).all() and (frames[0, :5] == 0).all()
    assert (frames[0, 5] != 0).any()
    for colours in (rgb, frames):
        back = np.asarray(codec.decode(torch.from_numpy(colours) if backend == "torch" else colours))
        assert (back[0, :5] == 0).all() and back[0, 5] == pytest.approx(0.7, rel=1e-3)


def test_black_tolerance_for_lossy_video():
    codec = DepthCodec()
    noisy_black = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 1], [3, 1, 0]], np.uint8)
    assert (codec.decode(noisy_black) > 0).tolist() == [False, True, True, True]
    assert (codec.decode(noisy_black, invalid_codes=2.5) > 0).tolist() == [False, False, False, True]
    nan_colour = np.array([np.nan, 0.5, 0.5], np.float32)
    assert codec.decode(nan_colour) == 0


# ---------------------------------------------------------------------- monotonicity
@pytest.mark.parametrize("preset", PRESET_NAMES)
def test_walk_is_monotonic_and_visits_the_corners_in_order(preset):
    codec = DepthCodec.preset(preset)
    d = np.geomspace(codec.min_depth, codec.max_depth, 400001)
    s = path_position(codec.encode(d))
    assert np.all(np.diff(s) > 0)  # strictly increasing along the walk
    # 8-bit frames: codes never go back, and the dense sweep skips none of them.
    codes = np.rint(path_position(codec.encode_uint8(d)) * 255).astype(int)
    assert codes[0] == 1 and codes[-1] == N_CODES - 1
    assert set(np.diff(codes).tolist()) <= {0, 1}
    # Corner j sits at walk position j (code 255 j).
    corner_depths = codec.depth_of_code(255 * np.arange(1, 7))
    corners = codec.encode_uint8(corner_depths)
    np.testing.assert_array_equal(corners, (WALK[1:7] * 255).astype(np.uint8))
    # Every segment moves exactly one channel.
    frames = codec.encode_uint8(d).astype(int)
    steps = np.abs(np.diff(frames, axis=0))
    assert np.all(steps.sum(axis=-1) <= 1)


# ----------------------------------------------------------------------- off the walk
def brute_force_position(colours, n_per_segment=2000):
    """Walk position of the nearest point on a dense sampling of the walk."""
    s_grid = np.linspace(0, 7, 7 * n_per_segment + 1)
    walk = oracle_colour(s_grid)
    d2 = ((colours[:, None, :] - walk[None, :, :]) ** 2).sum(-1)
    best = np.argmin(d2, axis=1)
    return s_grid[best], d2[np.arange(len(colours)), best]


def test_projection_matches_brute_force_nearest_point():
    colours = RNG.uniform(0, 1, (1000, 3))
    s_oracle, d2_oracle = brute_force_position(colours)
    s = path_position(colours)
    # Same nearest distance (the position may differ only where two segments tie).
    d2 = ((colours - oracle_colour(s)) ** 2).sum(-1)
    np.testing.assert_allclose(d2, d2_oracle, atol=2e-4)
    tie_free = np.abs(s - s_oracle) < 1e-3
    assert tie_free.mean() > 0.97


@pytest.mark.parametrize("backend", ["numpy", "torch"])
@pytest.mark.parametrize("preset", PRESET_NAMES)
def test_perturbed_colours_decode_near_the_true_depth(preset, backend):
    """Compression noise moves a colour off the walk; its projection moves along the
    walk by at most 2*sqrt(2)*|noise| (the walk turns by 90 degrees at corners and
    segments that do not touch are >= 1 apart), so the depth stays within that many
    codes of the truth."""
    codec = DepthCodec.preset(preset)
    d = np.exp(RNG.uniform(np.log(0.05), np.log(min(20.0, 0.9 * codec.max_depth)), 50000))
    frames = codec.encode_uint8(d.astype(np.float32)).astype(np.float64)
    noise = RNG.normal(0, 2.0, frames.shape)  # ~2 LSB of compression noise per channel
    noisy = np.clip(np.rint(frames + noise), 0, 255).astype(np.uint8)
    x = torch.from_numpy(noisy) if backend == "torch" else noisy
    back = np.asarray(codec.decode(x), np.float64)
    eps_codes = np.linalg.norm(noisy - frames, axis=-1)  # colour shift, in LSB
    code = 7 * 255 * oracle_f(d, codec.lam, codec.c)
    slack = 2 * np.sqrt(2) * eps_codes + 0.5 + 1e-3
    lo = codec.depth_of_code(np.maximum(code - slack, 1))
    hi = codec.depth_of_code(np.minimum(code + slack, N_CODES - 1))
    assert np.all((back >= lo * (1 - 1e-6)) & (back <= hi * (1 + 1e-6)))
    # In metres, typical error for 2-LSB noise is a few quantisation steps.
    typical = np.median(np.abs(back - d) / codec.quantisation_step(d))
    assert typical < 4


# --------------------------------------------------------------------------- autograd
def test_torch_gradients_are_finite():
    codec = DepthCodec()
    d = torch.tensor([0.0, float("nan"), 0.3, 1.0, 2.5], requires_grad=True)
    codec.encode(d).sum().backward()
    assert torch.isfinite(d.grad).all() and (d.grad[2:] != 0).all()
    assert (d.grad[:2] == 0).all()

    rgb = codec.encode(torch.tensor([0.2, 0.9, 1.7])).detach() + 0.01
    rgb.requires_grad_(True)
    codec.decode(rgb).sum().backward()
    assert torch.isfinite(rgb.grad).all() and (rgb.grad != 0).any()


def test_channel_axis():
    codec = DepthCodec()
    d = torch.rand(2, 4, 5) + 0.1
    frames = codec.encode_uint8(d, channel_axis=1)
    assert frames.shape == (2, 3, 4, 5)
    torch.testing.assert_close(frames.movedim(1, -1), codec.encode_uint8(d))
    back = codec.decode(frames, channel_axis=1)
    assert back.shape == d.shape
    torch.testing.assert_close(back, codec.decode(codec.encode_uint8(d)))


# ------------------------------------------------------------------------- bad input
@pytest.mark.parametrize(
    "depth",
    [np.full((2, 2), 800, np.uint16), np.full((2, 2), 800, np.int32), np.ones((2, 2), bool),
     torch.full((2, 2), 800, dtype=torch.int16)],
    ids=["uint16", "int32", "bool", "torch-int16"],
)
def test_integer_depth_points_to_millimetre_helper(depth):
    with pytest.raises(InputError, match="depth_from_millimetres"):
        DepthCodec().encode(depth)


@pytest.mark.parametrize("backend", ["numpy", "torch"])
def test_negative_depth_raises_with_its_name(backend):
    d = np.array([0.5, -0.25, np.nan, -1.0], np.float32)
    x = torch.from_numpy(d) if backend == "torch" else d
    with pytest.raises(InputError, match=r"episode 3 cam_high: 2 negative .*-1 m"):
        DepthCodec().encode_uint8(x, name="episode 3 cam_high")


@pytest.mark.parametrize(
    "colours, match",
    [(np.zeros((4, 4, 4), np.uint8), "3 channels"), (np.zeros((3, 4), np.uint8), "3 channels"),
     (np.zeros((), np.float32), "scalar"), (np.zeros((4, 3), np.int64), "uint8.*int64"),
     (np.zeros((4, 3), np.uint16), "uint16"), (torch.zeros(4, 4, dtype=torch.uint8), "3 channels"),
     (torch.zeros(4, 3, dtype=torch.int32), "int32")],
)
def test_bad_colours_raise(colours, match):
    with pytest.raises(InputError, match=match):
        DepthCodec().decode(colours)


def test_depth_from_millimetres():
    mm = np.array([[0, 1, 800], [65535, 250, 0]], np.uint16)
    m = depth_from_millimetres(mm)
    assert m.dtype == np.float32
    np.testing.assert_allclose(m, mm / 1000.0, rtol=1e-7)
    frames = DepthCodec().encode_uint8(m)
    assert (frames[0, 0] == 0).all() and (frames[1, 2] == 0).all()  # 0 mm stays invalid
    t = depth_from_millimetres(torch.from_numpy(mm.astype(np.int32)))
    assert t.dtype == torch.float32 and torch.allclose(t, torch.from_numpy(m))
    with pytest.raises(InputError, match="negative"):
        depth_from_millimetres(np.array([5, -3], np.int16))
    with pytest.raises(InputError, match="integer or float"):
        depth_from_millimetres(np.array(["5"]))
