"""Video metrics: MSE/PSNR/SSIM against hand formulas (scipy.ndimage for SSIM), FID
against torchmetrics' own FrechetInceptionDistance, the Fréchet formula against scipy's
matrix square root, and FID/FVD with randomly initialised extractors of the real
architectures (the weights cannot be downloaded here): ~0 on identical videos, growing
with the perturbation. Nothing may touch the network."""

import json
import math
import socket

import numpy as np
import pytest
import scipy.linalg
import torch
from scipy import ndimage

from imac_data.errors import InputError
from imac_model.evaluate import video_metrics as vm
from imac_model.evaluate.video_metrics import (
    FID_WEIGHTS_URL,
    FVD_WEIGHTS_URL,
    MissingWeightsError,
    VideoMetricsConfig,
    compute_video_metrics,
    frechet_distance,
    load_fid_extractor,
    load_fvd_extractor,
    save_random_weights,
)

PIXEL_ONLY = VideoMetricsConfig(metrics=("mse", "psnr", "ssim"))


def _refuse_network(mp: pytest.MonkeyPatch) -> None:
    def refuse(*args, **kwargs):
        raise AssertionError("network access attempted")

    mp.setattr(socket.socket, "connect", refuse)
    mp.setattr(socket, "create_connection", refuse)


@pytest.fixture()
def no_network(monkeypatch):
    _refuse_network(monkeypatch)


@pytest.fixture(scope="module")
def random_extractors(tmp_path_factory):
    """The real FID Inception and FVD I3D, randomly initialised, written to files and
    loaded back through the production loaders, with the network refused."""
    d = tmp_path_factory.mktemp("weights")
    with pytest.MonkeyPatch.context() as mp:
        _refuse_network(mp)
        fid = save_random_weights("fid", d / "fid.pth", seed=0)
        fvd = save_random_weights("fvd", d / "fvd.pt", seed=0)
        return load_fid_extractor(fid), load_fvd_extractor(fvd)


def ssim_oracle(x: np.ndarray, y: np.ndarray) -> float:
    """Wang et al. (2004) SSIM of two (3, H, W) images in [0, 1]: Gaussian window sigma 1.5
    truncated at radius 5 (11 taps), whole-sample mirror padding (torch's 'reflect'),
    population moments, k1 = 0.01, k2 = 0.03, averaged over pixels and channels."""
    c1, c2 = 0.01**2, 0.03**2
    maps = []
    for a, b in zip(x.astype(np.float64), y.astype(np.float64)):
        f = lambda im: ndimage.gaussian_filter(im, 1.5, truncate=5 / 1.5, mode="mirror")  # noqa: E731
        ma, mb = f(a), f(b)
        saa = np.maximum(f(a * a) - ma**2, 0)
        sbb = np.maximum(f(b * b) - mb**2, 0)
        sab = f(a * b) - ma * mb
        maps.append(((2 * ma * mb + c1) * (2 * sab + c2)) / ((ma**2 + mb**2 + c1) * (saa + sbb + c2)))
    return float(np.mean(maps))


def frames_metrics(gen: np.ndarray, rec: np.ndarray) -> dict:
    """Per-frame hand metrics of (N, T, 3, H, W) arrays, averaged over all frames."""
    g, r = gen.reshape(-1, *gen.shape[2:]).astype(np.float64), rec.reshape(-1, *rec.shape[2:]).astype(np.float64)
    mse = ((g - r) ** 2).mean(axis=(1, 2, 3))
    return {"mse": mse.mean(), "psnr": (10 * np.log10(1.0 / mse)).mean(),
            "ssim": np.mean([ssim_oracle(a, b) for a, b in zip(g, r)])}


def test_pixel_metrics_per_view_mosaic_and_task_match_hand_formulas():
    rng = np.random.default_rng(0)
    views = ("cam_high", "cam_left_wrist")
    rec = {v: rng.random((4, 3, 3, 24, 32)).astype(np.float32) for v in views}
    gen = {v: np.clip(rec[v] + rng.normal(0, 0.1, rec[v].shape), 0, 1).astype(np.float32) for v in views}
    gen["cam_left_wrist"][:2] = rec["cam_left_wrist"][:2] * 0.5  # task a's left view much worse
    tasks = ["a", "a", "b", "b"]
    out = compute_video_metrics(gen, rec, tasks=tasks, sampler_steps=10, seed=7, config=PIXEL_ONLY,
                                protocol_extra={"model": "tiny"})
    mosaic = lambda d: np.concatenate([d[v] for v in views], axis=-1)  # noqa: E731
    for task, rows in (("a", slice(0, 2)), ("b", slice(2, 4))):
        for key in (*views, "mosaic"):
            g, r = (mosaic(gen), mosaic(rec)) if key == "mosaic" else (gen[key], rec[key])
            expected = frames_metrics(g[rows], r[rows])
            for name, value in expected.items():
                assert out["per_task"][task][key][name] == pytest.approx(value, rel=1e-5, abs=1e-6), (task, key, name)
            assert out["per_task"][task][key]["n_samples"] == 2
    # the mosaic's MSE is the mean of its equal-sized views'
    assert out["per_task"]["a"]["mosaic"]["mse"] == pytest.approx(
        np.mean([out["per_task"]["a"][v]["mse"] for v in views]), rel=1e-6)
    # pooled over tasks, and mean +- std (ddof 0) over tasks
    for key in (*views, "mosaic"):
        g, r = (mosaic(gen), mosaic(rec)) if key == "mosaic" else (gen[key], rec[key])
        assert out["pooled"][key]["mse"] == pytest.approx(frames_metrics(g, r)["mse"], rel=1e-6)
        per = [out["per_task"][t][key]["psnr"] for t in ("a", "b")]
        assert out["mean_over_tasks"][key]["psnr"]["mean"] == pytest.approx(np.mean(per))
        assert out["mean_over_tasks"][key]["psnr"]["std"] == pytest.approx(np.std(per))
        assert out["mean_over_tasks"][key]["psnr"]["n_tasks"] == 2
    p = out["protocol"]
    assert p["frames"] == 3 and p["views"] == list(views) and p["num_samples"] == 4
    assert p["resolution"] == {v: [24, 32] for v in views}
    assert p["num_samples_per_task"] == {"a": 2, "b": 2}
    assert p["sampler_steps"] == 10 and p["seed"] == 7 and p["model"] == "tiny"
    json.loads(json.dumps(out))  # JSON-ready


def test_psnr_and_ssim_analytic_cases_and_uint8_input():
    base = torch.full((1, 2, 3, 16, 16), 0.5)
    out = compute_video_metrics({"v": base + 0.1}, {"v": base}, config=PIXEL_ONLY)["pooled"]["v"]
    assert out["mse"] == pytest.approx(0.01, rel=1e-5)
    assert out["psnr"] == pytest.approx(20.0, rel=1e-5)  # 10 log10(1 / 0.1^2)
    same = (torch.rand(2, 2, 3, 16, 16) * 255).to(torch.uint8)
    out = compute_video_metrics({"v": same}, {"v": same}, config=PIXEL_ONLY)["pooled"]["v"]
    assert out["mse"] == 0.0 and out["ssim"] == pytest.approx(1.0) and out["psnr"] == math.inf


def test_frechet_distance_matches_the_matrix_square_root_formula():
    rng = np.random.default_rng(1)
    a = rng.normal(0, 1, (400, 6)) @ rng.normal(0, 1, (6, 6))
    b = rng.normal(0.3, 1, (300, 6)) @ rng.normal(0, 1, (6, 6))
    ma, mb = a.mean(0), b.mean(0)
    sa, sb = np.cov(a, rowvar=False), np.cov(b, rowvar=False)
    expected = ((ma - mb) ** 2).sum() + np.trace(sa + sb - 2 * np.real(scipy.linalg.sqrtm(sa @ sb)))
    assert frechet_distance(a, b) == pytest.approx(expected, rel=1e-9)
    assert frechet_distance(a, a) == pytest.approx(0.0, abs=1e-9)


class PooledProjection(torch.nn.Module):
    """A small fixed feature extractor (uint8 frames of any size -> 48 features)."""

    def forward(self, x):
        return torch.nn.functional.adaptive_avg_pool2d(x.float() / 255.0, (4, 4)).flatten(1) ** 2


def test_fid_per_task_and_mosaic_equal_torchmetrics(no_network):
    from torchmetrics.image.fid import FrechetInceptionDistance

    g = torch.Generator().manual_seed(2)
    views = ("a", "b")
    rec = {v: torch.rand(6, 2, 3, 16, 20, generator=g) for v in views}
    gen = {v: (rec[v] + 0.2 * torch.rand(rec[v].shape, generator=g)).clamp(0, 1) for v in views}
    tasks = ["x"] * 3 + ["y"] * 3
    out = compute_video_metrics(gen, rec, tasks=tasks, fid_extractor=PooledProjection(),
                                config=VideoMetricsConfig(metrics=("fid",)))
    to_u8 = lambda t: (t * 255).round().to(torch.uint8).flatten(0, 1)  # noqa: E731
    for task, rows in (("x", slice(0, 3)), ("y", slice(3, 6))):
        for key in ("a", "mosaic"):
            pick = (lambda d: torch.cat([d[v][rows] for v in views], dim=-1)) if key == "mosaic" \
                else (lambda d: d[key][rows])
            oracle = FrechetInceptionDistance(feature=PooledProjection())
            oracle.update(to_u8(pick(rec)), real=True)
            oracle.update(to_u8(pick(gen)), real=False)
            assert out["per_task"][task][key]["fid"] == pytest.approx(float(oracle.compute()), rel=1e-4, abs=1e-7)
    oracle = FrechetInceptionDistance(feature=PooledProjection())
    oracle.update(to_u8(rec["b"]), real=True)
    oracle.update(to_u8(gen["b"]), real=False)
    assert out["pooled"]["b"]["fid"] == pytest.approx(float(oracle.compute()), rel=1e-4, abs=1e-7)


def test_fid_fvd_with_random_real_architectures(random_extractors, no_network):
    """Task 'same': generated == recorded; 'small' and 'large': Gaussian noise of sigma
    0.03 and 0.15 on the same recorded videos. FID and FVD must be ~0, then grow."""
    fid, fvd = random_extractors
    g = torch.Generator().manual_seed(3)
    recorded = torch.rand(2, 9, 3, 32, 32, generator=g)
    gen, rec, tasks = [], [], []
    for task, sigma in (("same", 0.0), ("small", 0.03), ("large", 0.15)):
        gen.append((recorded + sigma * torch.randn(recorded.shape, generator=g)).clamp(0, 1))
        rec.append(recorded)
        tasks += [task] * 2
    out = compute_video_metrics({"cam": torch.cat(gen)}, {"cam": torch.cat(rec)}, tasks=tasks, sampler_steps=4,
                                seed=0, fid_extractor=fid, fvd_extractor=fvd,
                                config=VideoMetricsConfig(metrics=("fid", "fvd"), fid_frame_stride=8))
    per = out["per_task"]
    for metric in ("fid", "fvd"):
        same, small, large = (per[t]["cam"][metric] for t in ("same", "small", "large"))
        print(metric, same, small, large)
        assert abs(same) < 1e-6 * large
        assert 0 < small < large
    assert "mosaic" not in per["same"]  # one view: no mosaic
    p = out["protocol"]
    assert p["config"]["fid_frame_stride"] == 8 and p["frames"] == 9
    assert p["definitions"]["fvd"]["weights"].endswith("fvd.pt")


def test_missing_weights_name_the_download(tmp_path, monkeypatch, no_network):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    expected_fid = tmp_path / "cache" / "imac" / "weights" / vm.FID_WEIGHTS_FILE
    with pytest.raises(MissingWeightsError) as e:
        load_fid_extractor()
    assert str(expected_fid) in str(e.value) and FID_WEIGHTS_URL in str(e.value)
    with pytest.raises(MissingWeightsError) as e:
        load_fvd_extractor(tmp_path / "elsewhere.pt")
    assert str(tmp_path / "elsewhere.pt") in str(e.value) and FVD_WEIGHTS_URL in str(e.value)
    assert vm.FVD_WEIGHTS_FILE in str(e.value)
    video = torch.rand(1, 9, 3, 16, 16)
    with pytest.raises(MissingWeightsError):  # before any work
        compute_video_metrics({"v": video}, {"v": video})
    bad = tmp_path / "bad.pt"
    torch.save({"conv.weight": torch.zeros(1)}, bad)
    with pytest.raises(InputError, match="not an I3D"):
        load_fvd_extractor(bad)


def test_bad_input(random_extractors):
    v = torch.rand(2, 4, 3, 16, 16)
    with pytest.raises(InputError, match=r"expected videos of shape \(N, T, 3, H, W\)"):
        compute_video_metrics({"v": v.permute(0, 1, 3, 4, 2)}, {"v": v}, config=PIXEL_ONLY)
    with pytest.raises(InputError, match="differ in shape"):
        compute_video_metrics({"v": v}, {"v": v[:, :3]}, config=PIXEL_ONLY)
    with pytest.raises(InputError, match=r"in \[0, 1\]"):
        compute_video_metrics({"v": v * 255}, {"v": v}, config=PIXEL_ONLY)
    with pytest.raises(InputError, match="views"):
        compute_video_metrics({"v": v}, {"w": v}, config=PIXEL_ONLY)
    with pytest.raises(InputError, match="3 names for 2 samples"):
        compute_video_metrics({"v": v}, {"v": v}, tasks=["a", "b", "c"], config=PIXEL_ONLY)
    with pytest.raises(InputError, match="mosaic needs views of one resolution"):
        compute_video_metrics({"v": v, "w": v[..., :8]}, {"v": v, "w": v[..., :8]}, config=PIXEL_ONLY)
    with pytest.raises(InputError, match="at least 9 frames"):
        compute_video_metrics({"v": v}, {"v": v}, fvd_extractor=random_extractors[1],
                              config=VideoMetricsConfig(metrics=("fvd",)))
    with pytest.raises(InputError, match="unknown"):
        VideoMetricsConfig(metrics=("lpips",))
    with pytest.raises(InputError, match="does not divide"):
        compute_video_metrics({"v": v, "w": v, "x": v}, {"v": v, "w": v, "x": v},
                              config=VideoMetricsConfig(metrics=("mse",), mosaic_rows=2))
