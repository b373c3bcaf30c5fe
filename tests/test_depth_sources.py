"""Depth sources: recorded depth, and the Depth Anything 3 plumbing.

No real DA3 weights can be downloaded here, so the DA3 tests use a randomly
initialised ``da3-small``: they check shapes, that our batched pipeline equals DA3's
own ``inference()``, the pose convention, scale handling and the errors, not the
accuracy of the depth. They are skipped when ``depth_anything_3`` is not importable
(install it with ``imac_data.sources.da3.DA3_INSTALL``).
"""

import importlib.util
import sys
import types

import numpy as np
import pytest

from imac_data.core.cameras import Camera, rescale_intrinsics
from imac_data.errors import InputError
from imac_data.sources.da3 import DepthAnything3, check_view_geometry
from imac_data.sources.depth import DepthSource, EpisodeViews, RecordedDepth

HAVE_DA3 = importlib.util.find_spec("depth_anything_3") is not None
needs_da3 = pytest.mark.skipif(not HAVE_DA3, reason="depth_anything_3 not installed (optional extra da3)")

H, W = 48, 64
K = np.array([[60.0, 0.0, 31.5], [0.0, 60.0, 23.5], [0.0, 0.0, 1.0]])


def look_at(centre, target=(0.0, 0.0, 0.0)):
    """Camera-to-world pose (OpenCV axes) of a camera at ``centre`` looking at ``target``."""
    c = np.asarray(centre, float)
    z = np.asarray(target, float) - c
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], axis=1)
    T[:3, 3] = c
    return T


CENTRES = ([0.8, 0.0, 0.6], [0.0, 0.7, 0.5], [-0.6, -0.3, 0.7])
TARGETS = ([0.1, 0.0, 0.0], [0.0, -0.1, 0.05], [0.05, 0.1, 0.0])


def rig(T=2, centres=CENTRES, seed=0):
    rng = np.random.default_rng(seed)
    images = [rng.integers(0, 256, (T, H, W, 3), dtype=np.uint8) for _ in centres]
    poses = [np.stack([look_at(c, tgt)] * T) for c, tgt in zip(centres, TARGETS)]
    return images, [K] * len(centres), poses


# ------------------------------------------------------------------ recorded depth
def test_recorded_depth_converts_and_resizes():
    mm = np.zeros((2, H // 2, W // 2), np.uint16)
    mm[0, 3, 4] = 1234
    mm[1] = 500
    views = EpisodeViews(images={"a": np.zeros((2, H, W, 3), np.uint8)},
                         cameras={"a": Camera("a", K, W, H, T_world_cam=np.eye(4))},
                         poses={"a": np.stack([np.eye(4)] * 2)}, depth_mm={"a": mm})
    src = RecordedDepth()
    assert isinstance(src, DepthSource)
    d = src.depth(views)["a"]
    assert d.dtype == np.float32 and d.shape == (2, H, W)  # resized to the image (nearest)
    assert np.allclose(d[0, 6:8, 8:10], 1.234)
    assert (d[0] > 0).sum() == 4 and np.allclose(d[1], 0.5)
    views.depth_mm = {"a": -np.ones((2, H, W), np.int32)}
    with pytest.raises(InputError, match="negative"):
        src.depth(views)
    views.depth_mm = {"a": np.ones((2, H, W, 1), np.uint16)}
    with pytest.raises(InputError, match=r"\(T, H, W\)"):
        src.depth(views)


# ------------------------------------------------------------------- view geometry
def test_view_geometry_checks():
    check_view_geometry(np.array(CENTRES))
    with pytest.raises(InputError, match="at least three views"):
        check_view_geometry(np.array(CENTRES[:2]))
    with pytest.raises(InputError, match="collinear"):
        check_view_geometry(np.array([[0, 0, 0], [1, 1, 0], [2, 2.005, 0]]))
    with pytest.raises(InputError, match="collinear"):
        check_view_geometry(np.zeros((3, 3)))
    ok = np.array(CENTRES)
    bad = np.array([[0, 0, 0], [0.5, 0, 0], [1.0, 0, 0]])
    with pytest.raises(InputError, match="first t=1"):
        check_view_geometry(np.stack([ok, bad, ok]))


def test_missing_package_is_a_clear_error(monkeypatch):
    monkeypatch.setitem(sys.modules, "depth_anything_3", None)  # import fails as if not installed
    with pytest.raises(InputError, match="pip install --no-deps depth-anything-3"):
        DepthAnything3("some/model", local_files_only=True)


# --------------------------------------------------------------- Depth Anything 3
@pytest.fixture(scope="module")
def da3():
    if not HAVE_DA3:
        pytest.skip("depth_anything_3 not installed (optional extra da3)")
    return DepthAnything3.random_init("da3-small", process_res=56, batch_size=2, device="cpu")


@needs_da3
def test_da3_shapes_and_source_interface(da3):
    images, Ks, poses = rig(T=3)
    images[2] = np.concatenate([images[2], images[2]], axis=2)  # another resolution: 48x128
    Ks = [K, K, rescale_intrinsics(K, (H, W), (H, 2 * W))]
    out = da3.depth(EpisodeViews(
        images=dict(zip("abc", images)), poses=dict(zip("abc", poses)),
        cameras={n: Camera(n, k, im.shape[2], im.shape[1], T_world_cam=np.eye(4))
                 for n, k, im in zip("abc", Ks, images)}))
    assert isinstance(da3, DepthSource)
    assert [out[n].shape for n in "abc"] == [(3, H, W), (3, H, W), (3, H, 2 * W)]
    assert all(o.dtype == np.float32 and np.isfinite(o).all() and (o > 0).all() for o in out.values())
    d = da3.describe()
    assert d["kind"] == "depth_anything_3" and d["weights"].startswith("random") and d["precision"] == "fp32"
    assert da3.processed_size(480, 640) == (42, 56) and da3.processed_size(H, W) == (42, 56)
    full = DepthAnything3.__new__(DepthAnything3)
    full.process_res = 504
    assert full.processed_size(480, 640) == (378, 504) and full.processed_size(240, 320) == (378, 504)


@needs_da3
def test_da3_pipeline_equals_da3_inference(da3):
    """One timestep through our batched pipeline == DA3's own inference() (fp32 on both sides)."""
    import cv2
    import torch

    images, Ks, poses = rig(T=1)
    net = da3._api_model
    h, w = da3.processed_size(H, W)
    interp = cv2.INTER_AREA if h * w < H * W else cv2.INTER_CUBIC  # DA3's own choice
    views = [cv2.resize(im[0], (w, h), interpolation=interp) for im in images]
    K_proc = np.stack([rescale_intrinsics(K, (H, W), (h, w))] * 3)
    w2c = np.linalg.inv(np.stack([p[0] for p in poses]))

    def fp32_forward(self, image, extrinsics=None, intrinsics=None, export_feat_layers=None, infer_gs=False,
                     use_ray_pose=False, ref_view_strategy="saddle_balanced"):
        with torch.inference_mode():
            return self.model(image, extrinsics, intrinsics, export_feat_layers, infer_gs, use_ray_pose,
                              ref_view_strategy)

    net.forward = types.MethodType(fp32_forward, net)  # DA3's own forward autocasts to fp16 on the CPU
    try:
        theirs = net.inference(views, extrinsics=w2c, intrinsics=K_proc, process_res=da3.process_res).depth
    finally:
        del net.forward
    c2w = np.stack(poses, axis=1)
    ours = da3._predict_processed(images, np.stack([np.broadcast_to(K, (1, 3, 3))] * 3, axis=1), c2w, range(1))
    np.testing.assert_allclose(ours[0], theirs, rtol=1e-5)


@needs_da3
def test_da3_batching_over_time_equals_one_call_per_timestep(da3):
    images, Ks, poses = rig(T=2)
    batched = da3.predict(images, Ks, poses)  # batch_size 2: one forward pass for both timesteps
    for t in range(2):
        single = da3.predict([im[t:t + 1] for im in images], Ks, [p[t:t + 1] for p in poses])
        for v in range(3):
            np.testing.assert_allclose(batched[v][t], single[v][0], rtol=1e-4)


@needs_da3
def test_da3_pose_convention_and_scale(da3):
    from scipy.spatial.transform import Rotation

    images, Ks, poses = rig(T=1)
    base = da3.predict(images, Ks, poses)
    # a rigid motion of the world changes nothing (DA3 sees world-to-camera poses)
    G = np.eye(4)
    G[:3, :3] = Rotation.from_euler("xyz", [0.3, -0.5, 1.0]).as_matrix()
    G[:3, 3] = [0.2, -1.0, 3.0]
    moved = da3.predict(images, Ks, [G @ p for p in poses])
    for a, b in zip(base, moved):
        np.testing.assert_allclose(a, b, rtol=1e-4)
    # ... which fails if the convention is wrong (camera-to-world handed over as world-to-camera)
    wrong = da3.predict(images, Ks, [np.linalg.inv(p) for p in poses])
    wrong_moved = da3.predict(images, Ks, [np.linalg.inv(G @ p) for p in poses])
    assert max(np.abs(a - b).max() / a.mean() for a, b in zip(wrong, wrong_moved)) > 1e-3
    # the world in other units: depth follows exactly (scale from the poses)
    scaled = []
    for p in poses:
        q = p.copy()
        q[:, :3, 3] *= 1000.0  # millimetres
        scaled.append(q)
    mm = da3.predict(images, Ks, scaled)
    for a, b in zip(base, mm):
        np.testing.assert_allclose(b, 1000.0 * a, rtol=1e-3)


@needs_da3
def test_da3_rejects_degenerate_views_before_running(da3):
    images, Ks, poses = rig(T=1)
    with pytest.raises(InputError, match="at least three views"):
        da3.predict(images[:2], Ks[:2], poses[:2])
    line = [[0.5, 0.2, 0.5], [0.7, 0.2, 0.5], [0.9, 0.2, 0.5]]
    images, Ks, poses = rig(T=1, centres=line)
    with pytest.raises(InputError, match="collinear"):
        da3.predict(images, Ks, poses)
    with pytest.raises(InputError, match="rigid"):
        da3.predict(images, Ks, [p * 2 for p in rig(T=1)[2]])
    with pytest.raises(InputError, match="uint8"):
        da3.predict([im.astype(np.float32) for im in rig(T=1)[0]], Ks, rig(T=1)[2])


@needs_da3
def test_da3_weights_from_a_local_directory_and_clear_errors_without_them(da3, tmp_path):
    images, Ks, poses = rig(T=1)
    weights = tmp_path / "weights"
    da3._api_model.save_pretrained(str(weights))  # config.json + model.safetensors, as the Hub has them
    loaded = DepthAnything3(weights, process_res=56, device="cpu")
    assert loaded.weights == "pretrained" and loaded.model == str(weights)
    for a, b in zip(da3.predict(images, Ks, poses), loaded.predict(images, Ks, poses)):
        np.testing.assert_allclose(a, b, rtol=1e-5)

    (weights / "model.safetensors").unlink()
    with pytest.raises(InputError, match="lacks"):
        DepthAnything3(weights)
    with pytest.raises(InputError, match="not available here"):
        DepthAnything3("depth-anything/DA3-SMALL", local_files_only=True)
    with pytest.raises(InputError, match="neither a directory"):
        DepthAnything3(tmp_path / "nowhere" / "deeper" / "x")
    with pytest.raises(InputError, match="multiple of 14"):
        DepthAnything3.random_init("da3-small", process_res=100)
