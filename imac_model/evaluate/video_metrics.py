"""Video metrics between generated and recorded future videos (the paper's Table 1).

MSE, PSNR and SSIM (torchmetrics), FID (torchmetrics' Inception) and FVD (``cd-fvd``'s I3D, at
least 9 frames per video), per view, on the mosaic and per task, pooled and as mean +- std over
tasks, with the protocol in the result. The extractors' weights are loaded from local files,
never downloaded (a missing file names its URL and place: ``docs/evaluation.md``); FID and FVD
from few samples are biased upwards, so compare them only at equal sample counts."""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from imac_data.errors import InputError
from imac_data.layout import cache_home

PIXEL_METRICS = ("mse", "psnr", "ssim")
FEATURE_METRICS = ("fid", "fvd")
METRICS = PIXEL_METRICS + FEATURE_METRICS
MOSAIC = "mosaic"
FVD_MIN_FRAMES = 9  # I3D: three temporal stride-2 stages, then a temporal pooling window of 2

FID_WEIGHTS_FILE = "weights-inception-2015-12-05-6726825d.pth"
FID_WEIGHTS_URL = ("https://github.com/toshas/torch-fidelity/releases/download/v0.2.0/"
                   "weights-inception-2015-12-05-6726825d.pth")
FVD_WEIGHTS_FILE = "i3d_pretrained_400.pt"
FVD_WEIGHTS_URL = "https://github.com/songweige/TATS/raw/main/tats/fvd/i3d_pretrained_400.pt"


class MissingWeightsError(InputError):
    """A feature extractor's weights file is not where it was looked for."""


# --------------------------------------------------------------------------- weights


def weights_dir() -> Path:
    """Where extractor weights are looked for by default: ``$XDG_CACHE_HOME/imac/weights``
    (``~/.cache/imac/weights``)."""
    return cache_home() / "weights"


def fid_weights_path() -> Path:
    return weights_dir() / FID_WEIGHTS_FILE


def fvd_weights_path() -> Path:
    return weights_dir() / FVD_WEIGHTS_FILE


def _require(path: Path, what: str, url: str, default: Path) -> Path:
    if path.is_file():
        return path
    raise MissingWeightsError(
        f"{what} weights not found at {path}. They cannot be downloaded at run time: fetch\n"
        f"  {url}\n"
        f"on a machine with internet access and put the file at {default}\n"
        f"  (mkdir -p {default.parent} && curl -L -o {default} {url})\n"
        f"or pass its path explicitly; or leave this metric out of `metrics`."
    )


class FIDFeatures(torch.nn.Module):
    """Frames ``(B, 3, H, W)`` uint8 -> the FID Inception's 2048-d pool features."""

    def __init__(self, inception: torch.nn.Module, weights: str):
        super().__init__()
        self.inception = inception
        self.weights = weights

    @torch.no_grad()
    def forward(self, frames: torch.Tensor) -> torch.Tensor:
        return self.inception(frames).double()


class FVDFeatures(torch.nn.Module):
    """Videos ``(B, T, H, W, 3)`` uint8 -> cd-fvd's I3D logits (400-d), with its preprocessing."""

    def __init__(self, i3d: torch.nn.Module, weights: str):
        super().__init__()
        self.i3d = i3d
        self.weights = weights

    @torch.no_grad()
    def forward(self, videos: torch.Tensor) -> torch.Tensor:
        from cdfvd.third_party.i3d.utils import preprocess_i3d

        if videos.shape[1] < FVD_MIN_FRAMES:
            raise InputError(f"FVD needs at least {FVD_MIN_FRAMES} frames per video (I3D's temporal pooling), "
                             f"got {videos.shape[1]}")
        device = next(self.i3d.parameters()).device
        x = preprocess_i3d(videos.cpu().numpy()).to(device)
        return self.i3d(x).double()


def _new_inception(weights: Path):
    from torchmetrics.image.fid import NoTrainInceptionV3

    return NoTrainInceptionV3(name="inception-v3-compat", features_list=["2048"],
                              feature_extractor_weights_path=str(weights))


def load_fid_extractor(weights: str | Path | None = None, device: str = "cpu") -> FIDFeatures:
    """The FID feature module from a local weights file (default :func:`fid_weights_path`)."""
    path = _require(Path(weights) if weights is not None else fid_weights_path(),
                    "FID (InceptionV3, torch-fidelity)", FID_WEIGHTS_URL, fid_weights_path())
    try:
        inception = _new_inception(path)
    except (RuntimeError, KeyError, OSError, ValueError) as e:
        raise InputError(f"{path}: not a torch-fidelity InceptionV3 state dict ({type(e).__name__}: {e})") from e
    return FIDFeatures(inception, str(path)).to(device).eval()


def load_fvd_extractor(weights: str | Path | None = None, device: str = "cpu") -> FVDFeatures:
    """The FVD feature module (cd-fvd's I3D) from a local checkpoint (default :func:`fvd_weights_path`).

    Built and loaded here rather than through ``cdfvd``'s own loader, which downloads
    the checkpoint when the path is missing.
    """
    from cdfvd.third_party.i3d.pytorch_i3d import InceptionI3d

    path = _require(Path(weights) if weights is not None else fvd_weights_path(),
                    "FVD (I3D, cd-fvd / TATS)", FVD_WEIGHTS_URL, fvd_weights_path())
    i3d = InceptionI3d(400, in_channels=3)
    try:
        i3d.load_state_dict(torch.load(path, map_location="cpu", weights_only=True))
    except (RuntimeError, KeyError, OSError, ValueError) as e:
        raise InputError(f"{path}: not an I3D (400 classes) state dict ({type(e).__name__}: {e})") from e
    return FVDFeatures(i3d, str(path)).to(device).eval()


def _he_init(module: torch.nn.Module, generator: torch.Generator) -> None:
    """He-normal weights, zero biases: activations keep their scale through the random
    network (PyTorch's default init makes the deep extractors' outputs nearly constant)."""
    for m in module.modules():
        if isinstance(m, (torch.nn.Conv2d, torch.nn.Conv3d, torch.nn.Linear)):
            fan_in = m.weight[0].numel()
            with torch.no_grad():
                m.weight.copy_(torch.randn(m.weight.shape, generator=generator) * math.sqrt(2.0 / fan_in))
                if m.bias is not None:
                    m.bias.zero_()


def save_random_weights(kind: str, path: str | Path, seed: int = 0) -> Path:
    """Write randomly initialised weights of the exact FID (``kind='fid'``) or FVD
    (``'fvd'``) extractor architecture to ``path``, loadable by the loaders above.
    For verifying the computation where the real weights cannot be had; the numbers
    they give mean nothing."""
    import tempfile

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    generator = torch.Generator().manual_seed(seed)
    if kind == "fvd":
        from cdfvd.third_party.i3d.pytorch_i3d import InceptionI3d

        net = InceptionI3d(400, in_channels=3)
    elif kind == "fid":
        from torchmetrics.image.fid import NoTrainInceptionV3

        class _Unloaded(NoTrainInceptionV3):
            def load_state_dict(self, state_dict, *args, **kwargs):  # keep the constructor's fresh layers
                if state_dict:
                    return super().load_state_dict(state_dict, *args, **kwargs)

        with tempfile.TemporaryDirectory() as tmp:
            empty = Path(tmp) / "empty.pth"
            torch.save({}, empty)
            net = _Unloaded(name="inception-v3-compat", features_list=["2048"],
                            feature_extractor_weights_path=str(empty))
    else:
        raise InputError(f"kind must be 'fid' or 'fvd', got {kind!r}")
    _he_init(net, generator)
    torch.save(net.state_dict(), path)
    return path


# --------------------------------------------------------------------------- Fréchet distance


def frechet_distance(a: torch.Tensor | np.ndarray, b: torch.Tensor | np.ndarray) -> float:
    """Fréchet distance between Gaussians fitted to two feature sets ``(n, d)`` (n >= 2):
    ``|mu_a - mu_b|^2 + tr(S_a + S_b) - 2 sum sqrt(eig(S_a S_b))`` in float64, the formula
    of torchmetrics' FID (robust to the singular covariances of few samples)."""
    a = torch.as_tensor(a, dtype=torch.float64)
    b = torch.as_tensor(b, dtype=torch.float64)
    if a.shape[0] < 2 or b.shape[0] < 2:
        raise InputError(f"the Fréchet distance needs at least 2 samples per set, got {a.shape[0]} and {b.shape[0]}")
    mu_a, mu_b = a.mean(0), b.mean(0)
    sa, sb = torch.cov(a.T).reshape(a.shape[1], -1), torch.cov(b.T).reshape(b.shape[1], -1)
    root = torch.linalg.eigvals(sa @ sb).sqrt().real.sum()
    return float((mu_a - mu_b).square().sum() + sa.trace() + sb.trace() - 2 * root)


# --------------------------------------------------------------------------- inputs


def _as_float_videos(name: str, x) -> torch.Tensor:
    t = torch.as_tensor(x)
    if t.ndim != 5 or t.shape[2] != 3:
        raise InputError(f"{name}: expected videos of shape (N, T, 3, H, W), got {tuple(t.shape)}")
    if t.dtype == torch.uint8:
        return t.float() / 255.0
    if not t.is_floating_point():
        raise InputError(f"{name}: expected uint8 or float frames, got {t.dtype}")
    t = t.float()
    if t.numel() and (not torch.isfinite(t).all() or t.min() < -1e-6 or t.max() > 1 + 1e-6):
        raise InputError(f"{name}: float frames must be finite and in [0, 1] "
                         f"(got range [{float(t.min()):.3g}, {float(t.max()):.3g}])")
    return t.clamp(0.0, 1.0)


def _to_uint8(x: torch.Tensor) -> torch.Tensor:
    return (x * 255.0).round().to(torch.uint8)


def tile_mosaic(views: Sequence[torch.Tensor], rows: int) -> torch.Tensor:
    """Tile per-view videos ``(..., 3, H, W)`` row-major into ``rows`` rows."""
    if len(views) % rows:
        raise InputError(f"mosaic_rows={rows} does not divide the {len(views)} views")
    cols = len(views) // rows
    return torch.cat([torch.cat(list(views[r * cols:(r + 1) * cols]), dim=-1) for r in range(rows)], dim=-2)


# --------------------------------------------------------------------------- accumulator


@dataclass(frozen=True)
class VideoMetricsConfig:
    """What :class:`VideoMetricAccumulator` computes."""

    metrics: tuple[str, ...] = METRICS
    mosaic_rows: int = 1  # 0: no mosaic
    feature_keys: tuple[str, ...] | None = None  # views (and "mosaic") that get FID/FVD; None: all
    fid_frame_stride: int = 1  # FID on every n-th frame of each video
    batch_size: int = 8  # videos per extractor call
    device: str = "cpu"

    def __post_init__(self) -> None:
        unknown = [m for m in self.metrics if m not in METRICS]
        if unknown or not self.metrics:
            raise InputError(f"VideoMetricsConfig.metrics: unknown {unknown}; choose from {METRICS}")
        for name, low in (("mosaic_rows", 0), ("fid_frame_stride", 1), ("batch_size", 1)):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < low:
                raise InputError(f"VideoMetricsConfig.{name}: must be an integer >= {low} (got {v!r})")
        object.__setattr__(self, "metrics", tuple(self.metrics))
        if self.feature_keys is not None:
            object.__setattr__(self, "feature_keys", tuple(self.feature_keys))


@dataclass
class _Sums:
    total: float = 0.0
    count: int = 0


@dataclass
class _State:
    pixel: dict = field(default_factory=lambda: defaultdict(_Sums))  # (task, key, metric) -> sums over frames
    features: dict = field(default_factory=lambda: defaultdict(list))  # (task, key, metric, side) -> [arrays]
    samples: dict = field(default_factory=lambda: defaultdict(int))  # task -> number of samples


class VideoMetricAccumulator:
    """Streams batches of (generated, recorded) videos and computes the metrics at the end.

    Memory: per-frame metric sums, plus one feature vector per FID frame (2048 floats)
    and per FVD video (400 floats); nothing that grows with the frames of a video
    beyond the batch being processed.
    """

    def __init__(self, views: Sequence[str], config: VideoMetricsConfig = VideoMetricsConfig(), *,
                 fid_extractor: torch.nn.Module | None = None, fvd_extractor: torch.nn.Module | None = None,
                 fid_weights: str | Path | None = None, fvd_weights: str | Path | None = None):
        self.views = tuple(views)
        if not self.views or len(set(self.views)) != len(self.views) or MOSAIC in self.views:
            raise InputError(f"views must be distinct names (not {MOSAIC!r}), got {list(views)}")
        self.config = config
        self.mosaic = config.mosaic_rows > 0 and len(self.views) > 1
        if self.mosaic and len(self.views) % config.mosaic_rows:
            raise InputError(f"mosaic_rows={config.mosaic_rows} does not divide the {len(self.views)} views")
        self.keys = self.views + ((MOSAIC,) if self.mosaic else ())
        if config.feature_keys is not None:
            bad = [k for k in config.feature_keys if k not in self.keys]
            if bad:
                raise InputError(f"VideoMetricsConfig.feature_keys: {bad} not among {list(self.keys)}")
        self.feature_keys = self.keys if config.feature_keys is None else tuple(config.feature_keys)
        # extractors first: a missing weights file is reported before any work
        self.fid = self.fvd = None
        if "fid" in config.metrics:
            self.fid = (load_fid_extractor(fid_weights) if fid_extractor is None else fid_extractor)
            self.fid = self.fid.to(config.device).eval()
        if "fvd" in config.metrics:
            self.fvd = (load_fvd_extractor(fvd_weights) if fvd_extractor is None else fvd_extractor)
            self.fvd = self.fvd.to(config.device).eval()
        self.state = _State()
        self.frames: int | None = None
        self.resolution: dict[str, list[int]] = {}

    def _check(self, generated: Mapping, recorded: Mapping, tasks: Sequence[str]) -> tuple[dict, dict, int]:
        for name, videos in (("generated", generated), ("recorded", recorded)):
            if set(videos) != set(self.views):
                raise InputError(f"{name}: views {sorted(videos)} do not match the expected {list(self.views)}")
        gen = {v: _as_float_videos(f"generated[{v!r}]", generated[v]) for v in self.views}
        rec = {v: _as_float_videos(f"recorded[{v!r}]", recorded[v]) for v in self.views}
        n, t = gen[self.views[0]].shape[:2]
        for v in self.views:
            if gen[v].shape != rec[v].shape:
                raise InputError(f"view {v!r}: generated {tuple(gen[v].shape)} and recorded {tuple(rec[v].shape)} "
                                 "videos differ in shape")
            if gen[v].shape[:2] != (n, t):
                raise InputError(f"view {v!r}: {tuple(gen[v].shape[:2])} samples x frames, "
                                 f"expected {(n, t)} like {self.views[0]!r}")
            hw = list(gen[v].shape[-2:])
            if self.resolution.setdefault(v, hw) != hw:
                raise InputError(f"view {v!r}: resolution {hw} differs from earlier batches' {self.resolution[v]}")
        if self.frames is None:
            self.frames = t
        elif self.frames != t:
            raise InputError(f"all videos must have the same number of frames: {t} here, {self.frames} before")
        if len(tasks) != n:
            raise InputError(f"tasks: {len(tasks)} names for {n} samples")
        if self.mosaic and len({tuple(x) for x in self.resolution.values()}) > 1:
            raise InputError(f"the mosaic needs views of one resolution, got {self.resolution}; "
                             "set mosaic_rows=0 to skip it")
        if self.fvd is not None and t < FVD_MIN_FRAMES:
            raise InputError(f"FVD needs at least {FVD_MIN_FRAMES} frames per video (I3D's temporal pooling), got {t}: "
                             "include the reference frame, evaluate longer rollouts, or leave 'fvd' out of metrics")
        return gen, rec, n

    @torch.no_grad()
    def update(self, generated: Mapping, recorded: Mapping, tasks: Sequence[str]) -> None:
        """Add a batch: ``generated[view]`` and ``recorded[view]`` are ``(N, T, 3, H, W)``,
        ``tasks`` one name per sample."""
        from torchmetrics.functional.image import peak_signal_noise_ratio
        from torchmetrics.functional.image import structural_similarity_index_measure as ssim
        from torchmetrics.functional.regression import mean_squared_error

        gen, rec, n = self._check(generated, recorded, tasks)
        tasks = [str(t) for t in tasks]
        for task in tasks:
            self.state.samples[task] += 1
        metrics, bs = self.config.metrics, self.config.batch_size
        for s in range(0, n, bs):
            part = slice(s, s + bs)
            dev = self.config.device
            chunk = {v: (gen[v][part].to(dev), rec[v][part].to(dev)) for v in self.views}
            if self.mosaic:
                rows = self.config.mosaic_rows
                chunk[MOSAIC] = (tile_mosaic([chunk[v][0] for v in self.views], rows),
                                 tile_mosaic([chunk[v][1] for v in self.views], rows))
            chunk_tasks = tasks[part]
            b = len(chunk_tasks)
            for key, (g, r) in chunk.items():
                t = g.shape[1]
                gf, rf = g.flatten(0, 1), r.flatten(0, 1)  # (b*T, 3, H, W)
                per_frame = {}
                if "mse" in metrics:
                    per_frame["mse"] = mean_squared_error(gf.flatten(1).T, rf.flatten(1).T, num_outputs=gf.shape[0])
                if "psnr" in metrics:
                    per_frame["psnr"] = peak_signal_noise_ratio(gf, rf, data_range=1.0, reduction="none", dim=(1, 2, 3))
                if "ssim" in metrics:
                    per_frame["ssim"] = ssim(gf, rf, data_range=1.0, reduction="none")
                for name, values in per_frame.items():
                    per_sample = values.double().reshape(b, t)
                    for i, task in enumerate(chunk_tasks):
                        sums = self.state.pixel[(task, key, name)]
                        sums.total += float(per_sample[i].sum())
                        sums.count += t
                if key not in self.feature_keys:
                    continue
                if self.fid is not None:
                    step = self.config.fid_frame_stride
                    for side, video in (("generated", g), ("recorded", r)):
                        frames = _to_uint8(video[:, ::step])
                        feats = self.fid(frames.flatten(0, 1)).cpu().reshape(b, frames.shape[1], -1)
                        for i, task in enumerate(chunk_tasks):
                            self.state.features[(task, key, "fid", side)].append(feats[i].numpy())
                if self.fvd is not None:
                    for side, video in (("generated", g), ("recorded", r)):
                        videos = _to_uint8(video).permute(0, 1, 3, 4, 2)  # (b, T, H, W, 3), cd-fvd's layout
                        feats = self.fvd(videos).cpu()
                        for i, task in enumerate(chunk_tasks):
                            self.state.features[(task, key, "fvd", side)].append(feats[i:i + 1].numpy())

    def _feature_metric(self, tasks: Sequence[str], key: str, metric: str) -> float | None:
        sides = []
        for side in ("generated", "recorded"):
            parts = [f for task in tasks for f in self.state.features.get((task, key, metric, side), [])]
            sides.append(np.concatenate(parts) if parts else np.zeros((0, 1)))
        if min(len(s) for s in sides) < 2:
            return None  # fewer than 2 samples: no covariance
        return frechet_distance(*sides)

    def _block(self, tasks: Sequence[str], key: str) -> dict:
        out = {}
        for metric in self.config.metrics:
            if metric in PIXEL_METRICS:
                total = sum(self.state.pixel[(t, key, metric)].total for t in tasks)
                count = sum(self.state.pixel[(t, key, metric)].count for t in tasks)
                out[metric] = total / count if count else None
            elif key in self.feature_keys:
                out[metric] = self._feature_metric(tasks, key, metric)
        return out

    def compute(self, *, sampler_steps: int | None = None, seed: int | None = None,
                protocol_extra: Mapping | None = None) -> dict:
        """The metrics and their protocol, as a JSON-ready dict."""
        if not self.state.samples:
            raise InputError("no videos were added")
        tasks = sorted(self.state.samples)
        per_task = {task: {key: self._block([task], key) | {"n_samples": self.state.samples[task]}
                           for key in self.keys} for task in tasks}
        pooled = {key: self._block(tasks, key) | {"n_samples": sum(self.state.samples.values())} for key in self.keys}
        over_tasks = {}
        for key in self.keys:
            over_tasks[key] = {}
            for metric in self.config.metrics:
                vals = [per_task[t][key].get(metric) for t in tasks]
                vals = np.array([v for v in vals if v is not None], dtype=np.float64)
                if metric not in pooled[key]:
                    continue
                with np.errstate(invalid="ignore"):  # PSNR of identical videos is +inf: its std is undefined
                    over_tasks[key][metric] = {
                        "mean": _json_float(vals.mean()) if vals.size else None,
                        "std": _json_float(vals.std()) if vals.size else None,
                        "n_tasks": int(vals.size),
                    }
        c = self.config
        protocol = {
            "frames": self.frames,
            "resolution": self.resolution,
            "views": list(self.views),
            "mosaic": {"rows": c.mosaic_rows, "order": "row-major over views"} if self.mosaic else None,
            "num_samples": sum(self.state.samples.values()),
            "num_samples_per_task": dict(sorted(self.state.samples.items())),
            "sampler_steps": sampler_steps,
            "seed": seed,
            "config": asdict(c) | {"feature_keys": list(self.feature_keys)},
            "definitions": {
                "mse": "mean over frames of the per-frame mean squared error, pixels in [0, 1]",
                "psnr": "mean over frames of the per-frame PSNR, data range 1 (inf for identical frames)",
                "ssim": "mean over frames of torchmetrics' Gaussian SSIM (11x11, sigma 1.5), data range 1",
                "fid": {"extractor": "torchmetrics NoTrainInceptionV3 (torch-fidelity TF-FID port), 2048-d pool",
                        "weights": getattr(self.fid, "weights", None), "frame_stride": c.fid_frame_stride,
                        "keys": list(self.feature_keys)} if self.fid is not None else None,
                "fvd": {"extractor": "cd-fvd InceptionI3d, Kinetics-400 logits, 224x224",
                        "weights": getattr(self.fvd, "weights", None),
                        "keys": list(self.feature_keys)} if self.fvd is not None else None,
                "std_over_tasks": "population standard deviation (ddof=0) of the per-task values",
            },
        }
        if protocol_extra:
            protocol.update(dict(protocol_extra))
        return {"protocol": protocol, "per_task": _clean(per_task), "pooled": _clean(pooled),
                "mean_over_tasks": over_tasks}


def _json_float(x) -> float | None:
    x = float(x)
    return None if math.isnan(x) else x


def _clean(tree):
    if isinstance(tree, dict):
        return {k: _clean(v) for k, v in tree.items()}
    if isinstance(tree, float):
        return _json_float(tree)
    return tree


def compute_video_metrics(generated: Mapping, recorded: Mapping, *, tasks: Sequence[str] | None = None,
                          sampler_steps: int | None = None, seed: int | None = None,
                          config: VideoMetricsConfig = VideoMetricsConfig(),
                          fid_extractor: torch.nn.Module | None = None, fvd_extractor: torch.nn.Module | None = None,
                          fid_weights: str | Path | None = None, fvd_weights: str | Path | None = None,
                          protocol_extra: Mapping | None = None) -> dict:
    """All metrics of ``generated`` vs ``recorded`` (``{view: (N, T, 3, H, W)}`` each),
    per view and mosaic, per task (``tasks``: one name per sample; default one task
    ``"all"``), pooled, and mean +- std over tasks; with the protocol. Extractors are
    loaded from local weights unless given (see the module docstring)."""
    views = list(generated)
    n = int(torch.as_tensor(generated[views[0]]).shape[0]) if views else 0
    tasks = ["all"] * n if tasks is None else list(tasks)
    acc = VideoMetricAccumulator(views, config, fid_extractor=fid_extractor, fvd_extractor=fvd_extractor,
                                 fid_weights=fid_weights, fvd_weights=fvd_weights)
    acc.update(generated, recorded, tasks)
    return acc.compute(sampler_steps=sampler_steps, seed=seed, protocol_extra=protocol_extra)
