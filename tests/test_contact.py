"""Contact images (imac_data.core.contact.images) against independent oracles: float64 brute force
(nearest distances), matplotlib (colour map), exact per-pixel queries (the certified
tolerance), an analytic plane, and MuJoCo's own geometric distances on recorded
simulated grasps (mj_geomDistance between the finger and cube geoms)."""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from imac_data.core.contact.batched import contact_batch
from imac_data.core.contact.images import (
    DEFAULT_TOLERANCE,
    EMPTY_CAP,
    JET_LUT,
    MIN_CAP,
    GripperSurface,
    NearestNeighbours,
    chunk_caps,
    chunk_plan,
    colorize,
    contact_chunk,
    dilate_mask,
    episode_contact,
    nearest_distances,
    scene_cloud,
)
from imac_data.core.contact.workspace import Workspace, resolve_workspace, saturation_depth
from imac_data.core.depth import DepthCodec
from imac_data.core.kdtree import kdtree
from imac_data.core.metric_depth import resize_depth
from imac_data.core.rig import Rig
from imac_data.core.robot.aloha import robot_config
from imac_data.core.robot.model import RobotModel
from imac_data.errors import InputError
from imac_data.sources.sim.env import FrameRenderer, robot_mask, segmentation_labels
from imac_data.sources.sim.recorder import simulate_episode
from imac_data.sources.sim.rig import camera_calibration, load_mujoco_model

METHODS = ["kdtree", "torch"]


def brute(query: np.ndarray, target: np.ndarray) -> np.ndarray:
    """float64 brute force, the oracle (|q|^2 + |t|^2 - 2 q.t in float64: the cancellation
    error, ~1e-16 of the squared coordinates, is far below float32 resolution)."""
    q = np.asarray(query, np.float64)
    t = np.asarray(target, np.float64)
    if len(t) == 0:
        return np.full(len(q), np.inf)
    t2 = (t * t).sum(1)
    out = np.empty(len(q))
    rows = max(1, (1 << 23) // len(t))
    for s in range(0, len(q), rows):
        b = q[s:s + rows]
        d2 = (b * b).sum(1)[:, None] + t2[None] - 2.0 * b @ t.T
        out[s:s + rows] = np.sqrt(np.maximum(d2.min(1), 0.0))
    return out


def check(query, target, method, max_distance=None, **kw):
    q = torch.as_tensor(query, dtype=torch.float32)
    t = torch.as_tensor(target, dtype=torch.float32)
    nn = NearestNeighbours(t, method=method, **kw)
    d, p = nn.query(q, max_distance=max_distance)
    ref = brute(q.numpy(), t.numpy())  # float32 coordinates, float64 arithmetic
    if max_distance is not None:
        ref = np.where(ref <= max_distance, ref, np.inf)
    assert d.dtype == torch.float32 and d.shape == (len(q),)
    np.testing.assert_allclose(d.numpy(), ref, rtol=1e-6, atol=1e-6)
    finite = torch.isfinite(d)
    assert torch.isnan(p[~finite]).all()
    if finite.any():  # the returned neighbour is a target point at that distance
        assert brute(p[finite].numpy(), t.numpy()).max() < 1e-6
        np.testing.assert_allclose((p[finite] - q[finite]).norm(dim=1).numpy(), d[finite].numpy(), atol=1e-5)
    return d


# ----------------------------------------------------------------------------- nearest distances


@pytest.mark.parametrize("method", METHODS)
def test_nearest_random_clouds_equal_brute_force(method):
    rng = np.random.default_rng(0)
    for n, m in [(1, 1), (7, 3), (500, 2000), (3000, 65)]:
        check(rng.normal(size=(n, 3)), rng.normal(size=(m, 3)) * 0.3, method)


@pytest.mark.parametrize("method", METHODS)
def test_nearest_adversarial_clouds(method):
    rng = np.random.default_rng(1)
    target = rng.uniform(-0.5, 0.5, (400, 3))
    # empty target: +inf; empty query: empty result
    d = check(rng.normal(size=(5, 3)), np.zeros((0, 3)), method)
    assert torch.isinf(d).all()
    assert check(np.zeros((0, 3)), target, method).shape == (0,)
    # single target point, and queries exactly on target points (distance 0)
    check(rng.normal(size=(50, 3)), target[:1], method)
    d = check(target[::7], target, method)
    assert (d == 0).all()
    # duplicated points in both clouds
    dup = np.repeat(target[:20], 30, axis=0)
    check(np.repeat(rng.normal(size=(10, 3)), 5, axis=0), dup, method)
    # far-apart clouds with a bound: culling changes nothing below the bound
    far = target + np.array([10.0, 0, 0])
    check(far, target, method, max_distance=0.5)  # all culled -> inf
    mixed = np.concatenate([far, target + 0.01 * rng.normal(size=target.shape), target[:50] + [0.7, 0, 0]])
    d = check(mixed, target, method, max_distance=0.3)
    assert torch.isinf(d).any() and torch.isfinite(d).any()
    check(mixed, target, method, max_distance=0.0)


def test_nearest_chunk_boundaries_and_large_n():
    rng = np.random.default_rng(2)
    q = rng.normal(size=(12011, 3))
    t = rng.normal(size=(997, 3))
    # small blocks: many torch chunks (rows of 53 queries), the last one partial
    check(q[:5011], t, "torch", chunk_pairs=997 * 53 + 5)
    check(q, t, "kdtree")
    check(q[:4000], t, "torch", max_distance=0.05, chunk_pairs=1000)


def test_nearest_on_a_layered_scene_is_exact():
    """A flat table with a few raised points (a zero-extent axis for most of the tree; the
    case that makes scipy's balanced cKDTree 20x slower): exact against brute force."""
    rng = np.random.default_rng(3)
    xy = rng.uniform(-0.5, 0.5, (30000, 2))
    table = np.c_[xy, np.zeros(len(xy))]
    box = rng.uniform([0.0, 0.0, 0.0], [0.04, 0.04, 0.04], (300, 3))
    target = np.concatenate([table, box])
    nn = NearestNeighbours(torch.as_tensor(target, dtype=torch.float32), method="kdtree")
    assert nn.method == "kdtree"
    query = rng.uniform([-0.6, -0.6, -0.1], [0.6, 0.6, 0.5], (3000, 3))
    check(query, target, "kdtree")
    check(query, target, "kdtree", max_distance=0.1)


def test_nearest_bad_input():
    with pytest.raises(InputError, match=r"\(N, 3\)"):
        nearest_distances(np.zeros((4, 2)), np.zeros((3, 3)))
    with pytest.raises(InputError, match="NaN or inf"):
        nearest_distances(np.full((2, 3), np.nan), np.zeros((3, 3)))
    with pytest.raises(InputError, match="method"):
        NearestNeighbours(np.zeros((3, 3)), method="faiss")
    with pytest.raises(InputError, match="max_distance"):
        nearest_distances(np.zeros((2, 3)), np.zeros((3, 3)), max_distance=-1.0)


def test_the_shared_kdtree_answers_what_scipys_answers():
    """core.kdtree (the contact streams' and calibration's tree) against scipy's cKDTree: the same distances and
    nearest points within a bound, inf and index n beyond it, for float64, float32 and strided queries, on a
    cloud with duplicate points; an empty cloud answers nothing within any distance, as scipy's does."""
    rng = np.random.default_rng(7)
    points = np.concatenate([rng.normal(size=(3000, 3)), np.repeat(rng.normal(size=(20, 3)), 3, axis=0)])
    queries = np.concatenate([rng.normal(size=(2000, 3)) * 1.5, points[::50] + 1e-9])
    ours, scipys = kdtree(points), cKDTree(points)
    for q in (queries, queries.astype(np.float32), np.repeat(queries, 2, axis=1)[:, ::2]):
        q64 = np.asarray(q, np.float64)
        for bound in (0.05, 0.3, np.inf):
            d, i = ours.query(q, distance_upper_bound=bound)
            d0, _ = scipys.query(q64, distance_upper_bound=bound)
            assert np.array_equal(np.isfinite(d), np.isfinite(d0)) and np.isfinite(d0).any()
            ok = np.isfinite(d0)
            assert np.allclose(d[ok], d0[ok], rtol=1e-6, atol=1e-6)  # float32 queries round once
            # the index names a point at the nearest distance (of duplicates, either one)
            assert np.allclose(np.linalg.norm(points[i[ok]] - q64[ok], axis=1), d0[ok], rtol=1e-6, atol=1e-6)
            assert (i[~ok] == len(points)).all()
    d, i = kdtree(np.zeros((0, 3))).query(queries[:5], distance_upper_bound=1.0)
    d0, _ = cKDTree(np.zeros((0, 3))).query(queries[:5], distance_upper_bound=1.0)
    assert np.array_equal(d, d0) and len(i) == 5


# ----------------------------------------------------------------------------- colours, masks, plan


def test_colorize_is_matplotlib_jet():
    import matplotlib

    cap = 0.3
    # distances at the centres of the 256 levels: no float boundary ambiguity
    d = cap * (1.0 - (np.arange(256) + 0.5) / 256.0)
    ours = colorize(torch.as_tensor(d, dtype=torch.float32), cap).numpy()
    ref = matplotlib.colormaps["jet"](1.0 - d / cap, bytes=True)[:, :3]
    np.testing.assert_array_equal(ours, ref)
    np.testing.assert_array_equal(JET_LUT, matplotlib.colormaps["jet"](np.arange(256), bytes=True)[:, :3])
    special = colorize(torch.tensor([0.0, cap, 5 * cap, math.inf, math.nan]), cap).numpy()
    np.testing.assert_array_equal(special, [[127, 0, 0], [0, 0, 127], [0, 0, 127], [0, 0, 127], [0, 0, 0]])
    with pytest.raises(InputError, match="cap"):
        colorize(torch.zeros(3), 0.0)


def test_dilate_mask_square():
    m = torch.zeros(2, 9, 9, dtype=torch.bool)
    m[0, 4, 4] = True
    out = dilate_mask(m, 2)
    assert out[0, 2:7, 2:7].all() and out[0].sum() == 25 and not out[1].any()
    assert torch.equal(dilate_mask(m, 0), m)


@pytest.mark.parametrize("radius", [1, 2, 3, 7])
def test_dilate_mask_against_brute_force(radius):
    """Every pixel within Chebyshev distance ``radius`` of a mask pixel, by brute force
    over all pixel pairs (odd shapes, masks at the borders, radius beyond the image)."""
    gen = torch.Generator().manual_seed(radius)
    m = torch.rand(3, 7, 11, generator=gen) > 0.93
    m[1, 0, 0] = m[2, 6, 10] = True
    y, x = torch.meshgrid(torch.arange(7), torch.arange(11), indexing="ij")
    near = (torch.maximum((y.reshape(-1, 1) - y.reshape(1, -1)).abs(),
                          (x.reshape(-1, 1) - x.reshape(1, -1)).abs()) <= radius)  # (HW, HW)
    want = (near[None] & m.reshape(3, 1, -1)).any(-1).reshape(3, 7, 11)
    assert torch.equal(dilate_mask(m, radius), want)


@pytest.mark.parametrize("T, H", [(1, 4), (5, 4), (9, 4), (10, 4), (23, 8), (3, 1)])
def test_chunk_plan(T, H):
    plan = chunk_plan(T, H)
    frames = [f for _, fs in plan for f in fs]
    assert frames == list(range(T))  # every frame exactly once, in order
    assert plan[0][0] == 0 and plan[0][1][0] == 0  # frame 0 = step 0 of chunk 0
    for c, (ref, fs) in enumerate(plan):
        assert ref == c * H
        steps = [f - ref for f in fs]
        assert all(1 <= k <= H for k in steps if not (c == 0 and k == 0))
    with pytest.raises(InputError):
        chunk_plan(0, 4)
    with pytest.raises(InputError):
        chunk_plan(5, 0)


# ----------------------------------------------------------------------------- an analytic scene


def _top_camera(H=48, W=64, height=1.0, f=60.0):
    K = torch.tensor([[f, 0, (W - 1) / 2], [0, f, (H - 1) / 2], [0, 0, 1.0]])
    T = torch.eye(4)
    T[:3, :3] = torch.diag(torch.tensor([1.0, -1.0, -1.0]))  # looking down -z, OpenCV axes
    T[2, 3] = height
    return K, T


def _plane_scene(S=3, H=48, W=64):
    """Top-down camera 1 m above the plane z = 0; a 'robot' plate parallel to the plane at
    heights h_k inside a pixel rectangle; 'gripper' points on a vertical line."""
    K, T = _top_camera(H, W)
    depth = torch.full((1, H, W), 1.0)
    rmask = torch.zeros(1, H, W, dtype=torch.bool)
    rmask[0, 2:8, 2:12] = True
    depth[0][rmask[0]] = 0.7  # the robot plate seen at the reference step
    heights = [0.3, 0.2, 0.05][:S]
    rdepth = torch.zeros(S, 1, H, W)
    for k, h in enumerate(heights):
        rdepth[k, 0, 20:40, 30:60] = 1.0 - h
    grip = [torch.tensor([[0.0, 0.0, z] for z in np.linspace(h, h + 0.1, 11)], dtype=torch.float32)
            for h in heights]
    return depth, K[None], T[None], rmask, rdepth, T[None].expand(S, 1, 4, 4), grip, heights


@pytest.mark.parametrize("tolerance", [None, (0.001, 0.02)])
def test_plane_distances_are_heights(tolerance):
    depth, K, T, rmask, rdepth, Tf, grip, heights = _plane_scene()
    c = contact_chunk(depth, K, T, rmask, rdepth, Tf, grip, tolerance=tolerance, fill_px=0)
    H, W = depth.shape[-2:]
    for k, h in enumerate(heights):
        r2s = c.r2s[k, 0]
        inside = rdepth[k, 0] > 0
        assert torch.isnan(r2s[~inside]).all()
        # the plate is parallel to the plane: its distance is its height up to the lateral
        # offset to the nearest plane sample (the plane is sampled every 1/60 m, the
        # camera's pixel footprint at 1 m): h <= d <= sqrt(h^2 + spacing^2 / 2)
        spacing = 1.0 / 60.0
        hi = math.sqrt(h * h + spacing ** 2 / 2) + (0 if tolerance is None else max(0.001, 0.02 * h))
        assert (r2s[inside] >= h - 1e-5).all() and (r2s[inside] <= hi + 1e-5).all()
        # s2g: distance from the plane point (x, y, 0) to the vertical segment at the
        # origin from z = h: sqrt(x^2 + y^2 + h^2), sampled every 1 cm above h
        scene = scene_cloud(depth, K, T, rmask, dilate_px=2)
        p = scene.points
        exact = torch.sqrt(p[:, 0] ** 2 + p[:, 1] ** 2 + h ** 2)
        got = c.s2g[k, 0].reshape(-1)[scene.flat]
        assert (got >= exact - 1e-5).all()
        slack = 1e-5 + (0 if tolerance is None else torch.clamp(0.02 * exact, min=0.001))
        assert (got <= torch.sqrt(p[:, 0] ** 2 + p[:, 1] ** 2 + h ** 2) + slack).all()
    # the (dilated) robot rectangle at the reference step is not scene: no s2g there
    assert torch.isnan(c.s2g[:, 0, 0:10, 0:14]).all()
    assert (c.caps > 0).all()


def test_fill_and_fixed_cap_semantics():
    depth, K, T, rmask, rdepth, Tf, grip, heights = _plane_scene()
    depth[0, 40, 5] = 0.0  # a one-pixel hole: filled from a neighbour
    depth[0, 30:48, 0:4] = 0.0  # a large invalid region: only its border is filled
    c = contact_chunk(depth, K, T, rmask, rdepth, Tf, grip, fill_px=2, tolerance=None)
    assert torch.isfinite(c.s2g[:, 0, 40, 5]).all()
    assert torch.isnan(c.s2g[:, 0, 35, 0:2]).all() and torch.isfinite(c.s2g[:, 0, 35, 2:4]).all()
    # fixed caps: distances beyond are +inf (saturated colour), caps are the given ones
    c = contact_chunk(depth, K, T, rmask, rdepth, Tf, grip, cap=(0.1, 0.25))
    assert c.caps.tolist() == pytest.approx([0.1, 0.25])
    assert torch.isinf(c.r2s[0][rdepth[0] > 0]).all()  # plate at 0.3 m > 0.1 m cap
    np.testing.assert_allclose(c.r2s[2][rdepth[2] > 0].numpy(), 0.05, atol=2e-3)
    assert (c.r2s_rgb[0][rdepth[0] > 0] == torch.tensor([0, 0, 127], dtype=torch.uint8)).all()
    s2g = c.s2g[~torch.isnan(c.s2g)]
    assert torch.isinf(s2g).any() and (s2g[torch.isfinite(s2g)] <= 0.25).all()


# ----------------------------------------------------------------------------- bad input


def test_bad_input_is_a_clear_input_error():
    depth, K, T, rmask, rdepth, Tf, grip, _ = _plane_scene()
    args = (depth, K, T, rmask, rdepth, Tf, grip)
    with pytest.raises(InputError, match=r"K must be \(V, 3, 3\)"):
        contact_chunk(depth, K.expand(2, 3, 3), *args[2:])
    with pytest.raises(InputError, match="camera poses must be"):
        contact_chunk(depth, K, T.expand(3, 4, 4), *args[3:])
    with pytest.raises(InputError, match="robot mask must be"):
        contact_chunk(depth, K, T, rmask[:, :5], *args[4:])
    with pytest.raises(InputError, match="future robot depth"):
        contact_chunk(*args[:4], torch.zeros(3, 2, 48, 64), Tf, grip)
    with pytest.raises(InputError, match="future camera poses"):
        contact_chunk(*args[:5], Tf[:2], grip)
    with pytest.raises(InputError, match="gripper points"):
        contact_chunk(*args[:6], grip[:2])
    with pytest.raises(InputError, match="no gripper"):
        contact_chunk(*args[:6], None)
    with pytest.raises(InputError, match="cap"):
        contact_chunk(*args, cap=-0.1)
    with pytest.raises(InputError, match="tolerance"):
        contact_chunk(*args, tolerance=(0.001, -1))
    # all-invalid depth, and a scene entirely covered by the robot
    with pytest.raises(InputError, match="no reference pixel has valid depth"):
        contact_chunk(torch.zeros_like(depth), *args[1:])
    with pytest.raises(InputError, match="inside the .* robot mask"):
        contact_chunk(depth, K, T, torch.ones_like(rmask), *args[4:])


def test_empty_clouds_have_defined_results():
    depth, K, T, rmask, rdepth, Tf, grip, _ = _plane_scene()
    c = contact_chunk(torch.zeros_like(depth), K, T, rmask, rdepth, Tf, grip, allow_empty_scene=True)
    robot = rdepth > 0
    assert torch.isinf(c.r2s[robot]).all() and torch.isnan(c.r2s[~robot]).all()
    assert torch.isnan(c.s2g).all()
    assert (c.r2s_rgb[robot] == torch.tensor([0, 0, 127], dtype=torch.uint8)).all()  # saturated
    assert (c.s2g_rgb == 0).all()  # black
    # an empty gripper cloud at a step: s2g saturated there only
    grip = [grip[0], torch.zeros(0, 3), grip[2]]
    c = contact_chunk(depth, K, T, rmask, rdepth, Tf, grip)
    s = c.s2g[1][~torch.isnan(c.s2g[1])]
    assert torch.isinf(s).all() and torch.isfinite(c.s2g[0][~torch.isnan(c.s2g[0])]).all()
    # no robot in view at all: nothing painted, caps still defined
    c = contact_chunk(depth, K, T, rmask, torch.zeros_like(rdepth), Tf, grip)
    assert torch.isnan(c.r2s).all() and torch.isfinite(c.caps).all()


def test_caps_are_numpys_percentile_over_what_has_a_value():
    """chunk_caps against numpy's own percentile (+inf stood in by a huge finite value): NaN ignored, +inf
    larger than everything, the largest finite value where the percentile lands on +inf, never below
    MIN_CAP, EMPTY_CAP without a finite value."""
    rng = np.random.default_rng(0)

    def oracle(v, q=99.0):
        v = v[~np.isnan(v)]
        if not np.isfinite(v).any():
            return EMPTY_CAP
        c = np.percentile(np.where(np.isinf(v), 1e30, v).astype(np.float64), q)
        return max(float(v[np.isfinite(v)].max()) if c >= 1e29 else c, MIN_CAP)

    for n, inf_share, nan_share in [(1, 0, 0), (7, 0.3, 0.2), (1000, 0.005, 0.1), (50_000, 0.02, 0), (300, 0.5, 0)]:
        r = rng.uniform(0, 0.4, n).astype(np.float32)
        r[rng.random(n) < inf_share] = np.inf
        r[rng.random(n) < nan_share] = np.nan
        s = rng.uniform(0, 0.2, (3, n)).astype(np.float32)
        caps = chunk_caps(torch.from_numpy(r), torch.from_numpy(s)).tolist()
        assert caps == pytest.approx([oracle(r), oracle(s.reshape(-1))], rel=1e-6), (n, inf_share, nan_share)
    for stream, expected in [(np.full(5, np.inf), EMPTY_CAP), (np.full(4, np.nan), EMPTY_CAP),
                             (np.zeros(0), EMPTY_CAP), (np.zeros(9), MIN_CAP)]:
        t = torch.from_numpy(stream.astype(np.float32))
        assert chunk_caps(t, t).tolist() == pytest.approx([expected, expected])


def test_robot_depth_without_a_finite_value_is_no_robot():
    """NaN and +inf in the future robot depth mark no robot, exactly as 0 does."""
    depth, K, T, rmask, rdepth, Tf, grip, _ = _plane_scene()
    robot = torch.nonzero(rdepth.reshape(-1) > 0)[:, 0]
    zero, odd = rdepth.clone().reshape(-1), rdepth.clone().reshape(-1)
    zero[robot[::3]] = 0.0
    odd[robot[::6]], odd[robot[3::6]] = math.inf, math.nan
    a = contact_chunk(depth, K, T, rmask, zero.reshape(rdepth.shape), Tf, grip)
    b = contact_chunk(depth, K, T, rmask, odd.reshape(rdepth.shape), Tf, grip)
    for name in ("r2s", "s2g", "r2s_rgb", "s2g_rgb", "caps"):
        torch.testing.assert_close(getattr(a, name), getattr(b, name), equal_nan=True, rtol=0, atol=0)


def test_episode_contact_caps_and_steps():
    depth, K, T, rmask, rdepth, Tf, grip, _ = _plane_scene(S=3)
    n = 7
    reps = [0, 1, 2, 0, 1, 2, 0]
    ep = episode_contact(depth.expand(n, 1, 48, 64), K, T.expand(n, 1, 4, 4), rmask.expand(n, 1, 48, 64),
                         rdepth[reps], Tf[reps], torch.stack([grip[i] for i in reps]), chunk_size=3)
    assert ep.r2s.shape == (n, 1, 48, 64) and ep.r2s_rgb.shape == (n, 1, 48, 64, 3)
    assert ep.reference.tolist() == [0, 0, 0, 0, 3, 3, 3]
    assert ep.step.tolist() == [0, 1, 2, 3, 1, 2, 3]
    assert torch.equal(ep.caps[0], ep.caps[3]) and torch.equal(ep.caps[4], ep.caps[6])


# ----------------------------------------------------------------------------- robot and MuJoCo


@pytest.fixture(scope="module")
def robot():
    return RobotModel(robot_config())


def test_gripper_surface_covers_the_finger_meshes(robot):
    g = GripperSurface(robot, spacing=0.002)
    assert set(g.links) == set(robot.gripper_links) and g.num_points > 4000
    for mesh in robot.visual_meshes:
        if mesh.link in g.links:
            d = brute(mesh.vertices, g.samples[mesh.link])
            assert d.max() <= 0.002 * math.sqrt(3) + 1e-6
    q = torch.zeros(2, robot.dof)
    q[1, 3] = 0.4
    poses = robot.link_poses(q)
    pts = g.points(poses)
    link = g.links[0]
    T = poses[link][1]
    local = torch.as_tensor(g.samples[link])
    np.testing.assert_allclose(pts[1, :len(local)].numpy(), (local @ T[:3, :3].T + T[:3, 3]).numpy(), atol=1e-6)



@pytest.fixture(scope="module")
def grasp(robot):
    """transfer_cube at 240x320, 25 fps, the first 2.4 s: the right gripper approaches,
    closes on and lifts the cube. Ground-truth depth and segmentation from MuJoCo."""
    model = load_mujoco_model("transfer_cube")
    cap = FrameRenderer(model, 320, 240, segmentation=True, keep_qpos=True)
    try:
        ep = simulate_episode("transfer_cube", seed=0, frame_stride=2, max_steps=120, renderer=cap)
    finally:
        cap.close()
    rig = Rig(robot, camera_calibration(model, 320, 240))
    names = rig.names
    depth = torch.stack([torch.as_tensor(ep.depth_mm[n].astype(np.float32) / 1000.0) for n in names], 1)
    seg = np.stack([ep.segmentation[n] for n in names], 1)
    q = torch.as_tensor(ep.qpos, dtype=torch.float32)
    views = rig.robot_views(q)
    inputs = {"mask": views.mask, "depth": views.depth, "T_world_cam": views.T_world_cam,
              "gripper_points": views.gripper_points}
    return dict(model=model, rig=rig, K=rig.intrinsics(), depth=depth, seg=seg, q=q, qfull=np.array(cap.qpos),
                inputs=inputs, labels=segmentation_labels(model))


def _mj_distance(model, data, g1, g2):
    """mj_geomDistance, or None when MuJoCo's answer is inconsistent with its own witness
    points (its native convex solver occasionally returns 0 with far-apart witnesses)."""
    fromto = np.zeros(6)
    d = mujoco.mj_geomDistance(model, data, g1, g2, 0.2, fromto)
    gap = np.linalg.norm(fromto[3:] - fromto[:3])
    if d < 0.2 and abs(gap - abs(d)) > 1e-4:
        return None
    return d


def test_scene_to_gripper_tracks_mujoco_distances(grasp):
    """Smallest s2g over the cube's reference pixels vs MuJoCo's finger-cube distance with
    the cube at its reference pose and the fingers at the future step (within 5 mm
    whenever MuJoCo's distance is under 5 cm), and robot pixels leaking into the scene
    cloud (by MuJoCo's segmentation) at most 1 %."""
    model, inp, labels = grasp["model"], grasp["inputs"], grasp["labels"]
    data = mujoco.MjData(model)
    box = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "red_box")
    adr = model.jnt_qposadr[model.body_jntadr[model.geom_bodyid[box]]]
    fingers = [g for g in range(model.ngeom) if "finger" in model.geom(g).name]
    assert len(fingers) == 4
    K = grasp["K"]
    T_frames = len(grasp["q"])
    errors, leaks, skipped = [], [], 0
    for ref, frames in chunk_plan(T_frames, 8):
        c = contact_chunk(grasp["depth"][ref], K, inp["T_world_cam"][ref], inp["mask"][ref], inp["depth"][frames],
                          inp["T_world_cam"][frames], inp["gripper_points"][frames])
        scene = scene_cloud(grasp["depth"][ref], K, inp["T_world_cam"][ref], inp["mask"][ref])
        robot_px = torch.as_tensor(robot_mask(grasp["seg"][ref], labels)).reshape(-1)
        leaks.append((int(robot_px[scene.flat].sum()), len(scene.flat)))
        cube = torch.as_tensor(grasp["seg"][ref] == box) & scene.valid
        assert cube.any()
        for i, f in enumerate(frames):
            data.qpos[:] = grasp["qfull"][f]
            data.qpos[adr:adr + 7] = grasp["qfull"][ref][adr:adr + 7]
            mujoco.mj_kinematics(model, data)
            dists = [_mj_distance(model, data, g, box) for g in fingers]
            if any(d is None for d in dists):
                skipped += 1
                continue
            mj = max(min(dists), 0.0)  # penetration (squeezing) counts as contact
            if mj < 0.05:
                ours = float(c.s2g[i][cube].min())
                errors.append((f, ref, mj, ours))
    errors = np.array(errors)
    assert len(errors) >= 20, "the episode should bring a finger within 5 cm of the cube"
    assert errors[:, 2].min() < 0.002, "the fingers should reach the cube"
    err = np.abs(errors[:, 3] - errors[:, 2])
    assert err.max() <= 0.005, errors[err.argmax()]
    assert skipped <= 0.25 * T_frames
    leak = sum(a for a, _ in leaks) / sum(b for _, b in leaks)
    assert leak <= 0.01 and max(a / b for a, b in leaks) <= 0.01


def test_tolerance_is_certified_on_recorded_frames(grasp):
    """Certified tolerance vs exact per-pixel distances on real inputs: every painted value
    within [exact, exact + max(abs, rel * exact)], colours almost all identical."""
    inp, K = grasp["inputs"], grasp["K"]
    ref, frames = 24, list(range(25, 33))  # approach and grasp
    args = (grasp["depth"][ref], K, inp["T_world_cam"][ref], inp["mask"][ref], inp["depth"][frames],
            inp["T_world_cam"][frames], inp["gripper_points"][frames])
    exact = contact_chunk(*args, tolerance=None, fill_px=0)
    for tol in [(0.001, 0.02), DEFAULT_TOLERANCE]:
        fast = contact_chunk(*args, tolerance=tol, fill_px=0)
        for name in ("r2s", "s2g"):
            a, b = getattr(fast, name), getattr(exact, name)
            assert torch.equal(torch.isnan(a), torch.isnan(b))
            m = ~torch.isnan(b)
            a, b = a[m], b[m]
            assert (a >= b - 1e-6).all()
            assert (a <= b + torch.clamp(tol[1] * b, min=tol[0]) + 1e-6).all()
            assert (a - b).mean() < 1e-4
            same = (getattr(fast, name + "_rgb") == getattr(exact, name + "_rgb")).all(-1).float().mean()
            assert same > 0.97
        np.testing.assert_allclose(fast.caps.numpy(), exact.caps.numpy(), rtol=0.02)


def test_torch_path_matches_kdtree_path(grasp):
    """The brute-force torch path (what runs on CUDA) gives the same distances as the
    KD-tree path (head camera only, to keep CPU brute force short): equal when exact; with
    the tolerance both are certified, and they differ only where the representative's
    nearest point is a tie."""
    inp, K = grasp["inputs"], grasp["K"]
    ref, frames, v = 40, [41, 44], slice(0, 1)
    args = (grasp["depth"][ref][v], K[v], inp["T_world_cam"][ref][v], inp["mask"][ref][v], inp["depth"][frames][:, v],
            inp["T_world_cam"][frames][:, v], inp["gripper_points"][frames])
    a = contact_chunk(*args, tolerance=None, method="kdtree")
    b = contact_chunk(*args, tolerance=None, method="torch")
    for name in ("r2s", "s2g"):
        torch.testing.assert_close(getattr(a, name), getattr(b, name), equal_nan=True, atol=2e-6, rtol=0)
    torch.testing.assert_close(a.caps, b.caps, atol=2e-6, rtol=0)
    tol = DEFAULT_TOLERANCE
    for method in ("kdtree", "torch"):
        c = contact_chunk(*args, tolerance=tol, method=method)
        for name in ("r2s", "s2g"):
            x, e = getattr(c, name), getattr(a, name)
            assert torch.equal(torch.isnan(x), torch.isnan(e))
            m = ~torch.isnan(e)
            assert (x[m] >= e[m] - 2e-6).all() and (x[m] <= e[m] + torch.clamp(tol[1] * e[m], min=tol[0]) + 2e-6).all()


def test_rig_contact_matches_the_episode_wiring(grasp):
    """Rig.contact (what a world model calls on its own depth) = the episode functions fed
    the same renders (what the dataset build calls)."""
    rig, inp = grasp["rig"], grasp["inputs"]
    n = 6
    ep = episode_contact(grasp["depth"][:n], grasp["K"], inp["T_world_cam"][:n], inp["mask"][:n], inp["depth"][:n],
                         inp["T_world_cam"][:n], inp["gripper_points"][:n], chunk_size=3)
    assert ep.r2s_rgb.shape == (n, 3, 240, 320, 3) and ep.caps.shape == (n, 2)
    c = rig.contact(grasp["depth"][3], grasp["q"][3], grasp["q"][4:6])
    assert ep.reference[4:].tolist() == [3, 3]
    torch.testing.assert_close(ep.r2s[4:6], c.r2s, equal_nan=True)
    torch.testing.assert_close(ep.s2g[4:6], c.s2g, equal_nan=True)
    assert torch.equal(ep.s2g_rgb[4:6], c.s2g_rgb) and torch.equal(ep.caps[4], c.caps)
    with pytest.raises(InputError, match="reference depth must be"):
        rig.contact(grasp["depth"][3][:2], grasp["q"][3], grasp["q"][4:6])


# ----------------------------------------------------------------------------- the workspace crop


def test_workspace_crop_on_the_plane():
    """Analytic: a box holding only x <= 0 of the plane and a depth range that rejects the
    saturated and the far pixels. The cropped cloud is exactly the in-box, in-range plane
    points; out-of-box pixels have no value (never hole-filled), out-of-range pixels are
    invalid depth (holes, filled at the border like 0); the caps are the percentile of the
    remaining points' brute-force distances."""
    depth, K, T, rmask, rdepth, Tf, grip, heights = _plane_scene()
    depth[0, 40:46, 18:24] = 65.535  # uint16 millimetres saturated
    depth[0, 10:14, 50:54] = 8.0  # a far wall, beyond the depth range
    ws = Workspace(min=(-1.0, -1.0, -0.05), max=(0.0, 1.0, 0.5), depth_range=(0.1, 4.0))
    full = scene_cloud(depth, K, T, rmask)
    scene = scene_cloud(depth, K, T, rmask, workspace=ws)
    in_range = (depth[0] >= 0.1) & (depth[0] < 4.0)
    keep = (full.points[:, 0] <= 0.0) & in_range.reshape(-1)[full.flat]
    assert torch.equal(scene.flat, full.flat[keep]) and torch.equal(scene.points, full.points[keep])
    assert (scene.points[:, 0] <= 0).all() and len(scene.points) > 1000
    c = contact_chunk(depth, K, T, rmask, rdepth, Tf, grip, tolerance=None, workspace=ws.to_dict())
    x = torch.arange(64, dtype=torch.float32) - 31.5  # pixel column -> x sign (camera x = world x)
    right = (x > 2)[None].expand(48, 64)  # x > 0 by more than the 2-pixel fill
    assert torch.isnan(c.s2g[:, 0][:, right]).all()
    assert torch.isnan(c.s2g[:, 0, 42:44, 20:22]).all()  # saturated: interior of a hole, no value
    assert torch.isfinite(c.s2g[:, 0, 40, 18:24]).all()  # its border is filled as any invalid depth
    for k in range(len(heights)):
        exact = brute(scene.points.double().numpy(), grip[k].double().numpy())
        np.testing.assert_allclose(c.s2g[k, 0].reshape(-1)[scene.flat].numpy(), exact, atol=2e-6)
    every = np.concatenate([brute(scene.points.double().numpy(), g.double().numpy()) for g in grip])
    assert float(c.caps[1]) == pytest.approx(np.percentile(every, 99), abs=2e-6)
    # without the crop the saturated pixels dominate the cap
    assert float(contact_chunk(depth, K, T, rmask, rdepth, Tf, grip).caps[1]) > 60


def _colour_distance(rgb: torch.Tensor, cap: float) -> torch.Tensor:
    """Stored s2g colours (..., 3) back to metres: the middle of the distance interval of the
    colour's level (level l <=> d in (cap (1 - (l+1)/256), cap (1 - l/256)]); NaN for black.
    matplotlib's jet repeats 3 of its 256 colours: the nearer level is taken."""
    key = lambda c: (c[..., 0] << 16) | (c[..., 1] << 8) | c[..., 2]  # noqa: E731
    lut_keys = key(torch.as_tensor(JET_LUT, dtype=torch.int64))
    level_of = dict(zip(lut_keys.tolist(), range(256)))  # later (nearer) levels overwrite
    keys, inverse = torch.unique(key(rgb.to(torch.int64)), return_inverse=True)
    levels = torch.tensor([level_of.get(k, -1) for k in keys.tolist()])[inverse]
    assert ((levels >= 0) | (rgb == 0).all(-1)).all(), "a painted colour is not a jet colour"
    d = cap * (1 - (levels.double() + 0.5) / 256)
    return torch.where(levels >= 0, d, torch.full_like(d, math.nan))


def test_workspace_crop_keeps_far_and_saturated_depth_out_of_the_caps(grasp):
    """A recorded grasp whose reference depth gets a far background (8 m: the head camera's
    upper rows, a wrist camera's lower rows) and uint16-saturated pixels (65.535 m, 2 % of
    every view). With the default workspace (the robot's reach, the codec's depth range)
    the stored s2g colour over the cube still gives MuJoCo's finger-cube distance within
    5 mm + half a colour level at a workspace-sized cap, and the caps stay within the
    workspace's diagonal; without the crop the s2g cap is tens of metres."""
    model, inp, rig = grasp["model"], grasp["inputs"], grasp["rig"]
    ws = resolve_workspace(None, rig.robot, saturation_depth(DepthCodec.preset("manipulation")))
    data = mujoco.MjData(model)
    box = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "red_box")
    adr = model.jnt_qposadr[model.body_jntadr[model.geom_bodyid[box]]]
    fingers = [g for g in range(model.ngeom) if "finger" in model.geom(g).name]
    K, rng = grasp["K"], np.random.default_rng(0)
    tol = 0.005 + ws.diagonal / 512
    errors = []
    T_frames = len(grasp["q"])
    for ref in (24, 48, 56):  # approach, closing in, squeezing the cube
        frames = list(range(ref + 1, min(ref + 9, T_frames)))
        cube = torch.as_tensor(grasp["seg"][ref] == box)
        depth = grasp["depth"][ref].clone()
        far = torch.zeros_like(cube)
        far[0, :60], far[1, 200:] = True, True
        depth[far & ~cube] = 8.0
        saturated = torch.as_tensor(rng.random(cube.shape) < 0.02) & ~cube
        depth[saturated] = 65.535
        args = (depth, K, inp["T_world_cam"][ref], inp["mask"][ref], inp["depth"][frames], inp["T_world_cam"][frames],
                inp["gripper_points"][frames])
        c = contact_chunk(*args, workspace=ws)
        assert (c.caps <= ws.diagonal).all(), c.caps
        if ref == 24:
            assert float(contact_chunk(*args).caps[1]) > 10 * ws.diagonal  # the poisoned scene, uncropped
        scene = scene_cloud(depth, K, inp["T_world_cam"][ref], inp["mask"][ref], workspace=ws)
        assert ws.contains(scene.points).all() and not scene.valid[far | saturated].any()
        cube &= scene.valid
        stored = _colour_distance(c.s2g_rgb[:, cube], float(c.caps[1]))  # (S, cube pixels)
        for i, f in enumerate(frames):
            data.qpos[:] = grasp["qfull"][f]
            data.qpos[adr:adr + 7] = grasp["qfull"][ref][adr:adr + 7]
            mujoco.mj_kinematics(model, data)
            dists = [_mj_distance(model, data, g, box) for g in fingers]
            if any(d is None for d in dists):
                continue
            mj = max(min(dists), 0.0)
            if mj < 0.05:
                errors.append((mj, float(c.s2g[i][cube].min()), float(stored[i].min())))
    errors = np.array(errors)
    assert len(errors) >= 12 and errors[:, 0].min() < 0.002
    assert np.abs(errors[:, 1] - errors[:, 0]).max() <= 0.005  # the distances themselves
    assert np.abs(errors[:, 2] - errors[:, 0]).max() <= tol, errors  # what the dataset stores


# ----------------------------------------------------------------------------- batched (the accelerator's form)


def test_batched_contact_is_contact_chunk_on_real_frames(grasp):
    """contact_batch (blocked brute force, what a GPU rebuilds a rollout's contact images with) against
    contact_chunk with exact searches, per chunk, on MuJoCo's depth and the rig's renders at 30x40 (approach,
    grasp and lift; the rig's workspace crop; every 8th gripper sample, to keep the CPU's brute force short), with
    blocks small enough to split items and rows: the same NaN pattern, distances within 2e-6 m, the same caps,
    colours within a level."""
    rig, hw = grasp["rig"], (30, 40)
    refs = [16, 24, 40]
    frames = [list(range(r + 1, r + 5)) for r in refs]
    seen = rig.robot_views(grasp["q"][refs], resolution=hw, gripper=False)
    drawn = rig.robot_views(grasp["q"][sum(frames, [])], resolution=hw)
    drawn.gripper_points = drawn.gripper_points[:, ::8]
    V = len(rig.names)
    depth = resize_depth(grasp["depth"][refs], hw)
    K = rig.intrinsics(hw)
    B, S = len(refs), 4
    got = contact_batch(depth, K, seen.T_world_cam, seen.mask, drawn.depth.reshape(B, S, V, *hw),
                        drawn.T_world_cam.reshape(B, S, V, 4, 4), drawn.gripper_points.reshape(B, S, -1, 3),
                        workspace=rig.workspace, method="brute", block=200_000)
    for b in range(B):
        want = contact_chunk(depth[b], K, seen.T_world_cam[b], seen.mask[b], drawn.depth[b * S:(b + 1) * S],
                             drawn.T_world_cam[b * S:(b + 1) * S], drawn.gripper_points[b * S:(b + 1) * S],
                             tolerance=None, workspace=rig.workspace)
        for name in ("r2s", "s2g"):
            torch.testing.assert_close(getattr(got, name)[b], getattr(want, name), equal_nan=True, atol=2e-6, rtol=0)
            assert (getattr(got, name + "_rgb")[b].int() - getattr(want, name + "_rgb").int()).abs().max() <= 1
        torch.testing.assert_close(got.caps[b], want.caps, atol=2e-6, rtol=0)
        assert torch.isfinite(want.r2s[~torch.isnan(want.r2s)]).all() and (~torch.isnan(want.s2g)).sum() > 100


def test_batched_contact_pads_empty_scenes_and_fixed_caps_as_contact_chunk():
    """Chunks of different sizes in one batch (one with no valid reference depth: an empty scene, one with
    no robot at a step), percentile and fixed caps, hole filling, brute force and KD-trees: every chunk as
    contact_chunk paints it alone (exact searches, allow_empty_scene)."""
    g = torch.Generator().manual_seed(0)
    B, S, V, H, W, M = 3, 3, 2, 10, 12, 40
    K = torch.tensor([[12.0, 0, 5.5], [0, 12.0, 4.5], [0, 0, 1]]).expand(V, 3, 3).clone()
    T_ref = torch.eye(4).expand(B, V, 4, 4).clone()
    T_ref[..., :3, 3] = 0.05 * torch.randn(B, V, 3, generator=g)
    T = torch.eye(4).expand(B, S, V, 4, 4).clone()
    T[..., :3, 3] = 0.05 * torch.randn(B, S, V, 3, generator=g)
    depth = 0.6 + 0.2 * torch.rand(B, V, H, W, generator=g)
    depth[0, 0, :4] = 0.0
    depth[1, 1, 2, 3] = float("nan")
    depth[2] = 0.0  # nothing in the scene
    mask = torch.rand(B, V, H, W, generator=g) < 0.15
    robot = torch.rand(B, S, V, H, W, generator=g) < 0.3
    robot[1, 2] = False  # a step without the robot in view
    rd = torch.where(robot, 0.4 + 0.2 * torch.rand(B, S, V, H, W, generator=g), 0.0)
    grip = 0.1 * torch.randn(B, S, M, 3, generator=g) + torch.tensor([0.0, 0.0, 0.6])
    for cap, method in ((None, "brute"), ((0.05, 0.08), "brute"), (None, "kdtree")):
        got = contact_batch(depth, K, T_ref, mask, rd, T, grip, cap=cap, fill_px=1, method=method)
        for b in range(B):
            want = contact_chunk(depth[b], K, T_ref[b], mask[b], rd[b], T[b], grip[b], cap=cap, fill_px=1,
                                 tolerance=None, allow_empty_scene=True)
            for name in ("r2s", "s2g"):
                torch.testing.assert_close(getattr(got, name)[b], getattr(want, name), equal_nan=True, atol=1e-6,
                                           rtol=0)
                assert torch.equal(getattr(got, name + "_rgb")[b], getattr(want, name + "_rgb"))
            torch.testing.assert_close(got.caps[b], want.caps, atol=1e-6, rtol=0)
    assert torch.isinf(got.r2s[2][robot[2]]).all() and torch.isnan(got.s2g[2]).all()
    with pytest.raises(InputError, match=r"gripper points must be \(B, S, M, 3\)"):
        contact_batch(depth, K, T_ref, mask, rd, T, grip[:, :1])
    grip[0, 0, 0, 0] = float("nan")
    with pytest.raises(InputError, match="gripper points contain NaN"):
        contact_batch(depth, K, T_ref, mask, rd, T, grip)
