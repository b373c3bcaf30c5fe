"""Depth Anything 3 as a depth source: multi-view metric depth, and its monocular metric model.

``depth-anything-3`` is an optional dependency (``make da3``; :data:`DA3_INSTALL`), imported
on first use. Its weights are never downloaded at run time: give a local directory or a hub
id already in the cache. Only the plumbing is verified here, with random weights
(``docs/depth-sources.md`` says what was checked).
"""

from __future__ import annotations

import importlib.metadata
import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from imac_data.core.cameras import rescale_intrinsics
from imac_data.errors import InputError
from imac_data.sources.episode import EpisodeViews

__all__ = ["DA3_INSTALL", "DEFAULT_DA3_MODEL", "DEFAULT_DA3_METRIC_MODEL", "DepthAnything3", "DepthAnything3Metric",
           "check_view_geometry", "looks_like_hub_id", "uses_monocular", "da3_model", "check_da3_inputs",
           "make_da3_source"]

# How to install the optional extra (depth-anything-3 0.1.1 pins numpy<2, so it is
# installed without its dependency resolution, plus the modules it imports).
# Everything else it imports (torch, torchvision, einops, safetensors, huggingface-hub,
# opencv, trimesh, imageio, pillow) comes with lerobot; xformers is optional.
DA3_INSTALL = (
    "pip install --no-deps depth-anything-3==0.1.1 omegaconf==2.3.0 antlr4-python3-runtime==4.9.3 "
    "addict==2.4.0 evo==1.38.1 moviepy==1.0.3 decorator==5.3.1 proglog==0.1.12 imageio-ffmpeg==0.8.1 "
    "pycolmap==4.2.1 plyfile==1.1.5"
)
# DA3-BASE: Apache-2.0 weights (DA3-LARGE / -GIANT are CC BY-NC 4.0).
DEFAULT_DA3_MODEL = "depth-anything/DA3-BASE"
# DA3's monocular metric model (preset da3metric-large): metres = focal * output / 300.
DEFAULT_DA3_METRIC_MODEL = "depth-anything/DA3METRIC-LARGE"
DA3_METRIC_FOCAL_SCALE = 300.0  # depth_anything_3.utils.alignment.apply_metric_scaling


def check_view_geometry(centres: np.ndarray, *, collinear_tol: float = 1e-2, where: str = "views") -> None:
    """Raise :class:`InputError` unless ``centres`` (``(N, 3)`` or ``(T, N, 3)``, camera
    centres in the world) has N >= 3 views whose centres span a plane at every time.

    Collinear means the second singular value of the centred centres is below
    ``collinear_tol`` times the first (default 1 %: the centres lie within about 1 %
    of their spread from a line); coincident means a spread below 1 micrometre.
    Depth Anything 3 takes its scale from a similarity fit of its own predicted
    camera poses to these; with fewer views or degenerate centres that fit is not
    determined and the depth would silently get a wrong scale.
    """
    c = np.asarray(centres, dtype=np.float64)
    if c.ndim == 2:
        c = c[None]
    if c.ndim != 3 or c.shape[-1] != 3:
        raise InputError(f"{where}: camera centres must be (N, 3) or (T, N, 3); got {np.shape(centres)}")
    n = c.shape[1]
    if n < 3:
        raise InputError(
            f"{where}: Depth Anything 3 needs at least three views with known poses to fix the metric scale; "
            f"got {n}"
        )
    if not np.isfinite(c).all():
        raise InputError(f"{where}: camera poses contain non-finite values")
    s = np.linalg.svd(c - c.mean(axis=1, keepdims=True), compute_uv=False)  # (T, 3)
    bad = np.flatnonzero((s[:, 0] < 1e-6) | (s[:, 1] < collinear_tol * s[:, 0]))
    if bad.size:
        t = int(bad[0])
        raise InputError(
            f"{where}: camera centres are collinear (or coincident) at {bad.size} timestep(s), first t={t} "
            f"(centres {np.round(c[t], 4).tolist()}); Depth Anything 3's scale would be undetermined"
        )


def _import_da3():
    try:
        from depth_anything_3 import api
        from depth_anything_3.utils.pose_align import align_poses_umeyama
    except ImportError as e:
        raise InputError(
            f"Depth Anything 3 is not installed ({e}). Install the optional extra: `make da3`, i.e. {DA3_INSTALL}"
        ) from e
    return api, align_poses_umeyama


def looks_like_hub_id(model: str) -> bool:
    parts = model.split("/")
    return len(parts) == 2 and all(parts) and not model.startswith((".", "~")) and os.sep not in model.replace("/", "")


def _nearest_multiple(x: float, p: int) -> int:
    down = int(x // p) * p
    up = down + p
    return max(p, up if abs(up - x) <= abs(x - down) else down)


class DepthAnything3:
    """Multi-view metric depth from Depth Anything 3 (``depth-anything-3`` 0.1.1).

    Each timestep's views (>= 3, non-collinear camera centres: see
    :func:`check_view_geometry`) go through the network together with their
    intrinsics and world-to-camera extrinsics (our poses are camera-to-world and are
    inverted here). DA3 predicts depth and its own camera poses; a Umeyama Sim(3) fit
    of its poses to ours (DA3's own ``align_poses_umeyama``, as in its
    ``inference(..., align_to_input_ext_scale=True)``) gives the scale, and depth is
    divided by it: depth comes out in the units of our poses, metres.

    Pipeline per batch of ``batch_size`` timesteps: every view is resized to the
    processing size (long side ``process_res``, both sides multiples of 14, the size
    DA3's ``upper_bound_resize`` picks for the first view; K follows with
    :func:`~imac_data.core.cameras.rescale_intrinsics`), normalised by DA3's
    ``InputProcessor``, extrinsics normalised per timestep by DA3's
    ``_normalize_extrinsics``, one forward pass of the network on ``(B, N, 3, h, w)``,
    scale alignment per timestep, and the depth is resized back to each view's
    stored resolution (bilinear; non-finite or non-positive values -> 0 = invalid).
    For one timestep this is DA3's ``inference()`` (``tests/test_depth_sources.py``
    checks they agree); batching over time is ours (``inference()`` takes one
    multi-view set per call).

    ``model``: a Hugging Face model id (default :data:`DEFAULT_DA3_MODEL`) or a local
    directory holding ``config.json`` + ``model.safetensors`` (what
    ``huggingface-cli download <id> --local-dir DIR`` writes). Weights that cannot be
    found raise :class:`InputError` saying how to get them; ``local_files_only=True``
    never touches the network (otherwise an offline machine spends about a minute in
    retries first). ``device``: ``"cuda"``, ``"cpu"``, ... (default: CUDA when
    available). ``precision``: ``"auto"`` = DA3's own autocast on CUDA (bf16 where
    supported, else fp16) and fp32 on the CPU (DA3's fp16 autocast is about 5x
    slower there), or ``"fp32"`` / ``"bf16"`` / ``"fp16"``.

    What was verified here (no real weights can be downloaded on our machines; all
    with randomly initialised ``da3-small``): shapes and resolutions, that the
    pipeline equals DA3's own ``inference()`` for one timestep, that batching over
    time equals one call per timestep, the pose convention (depth invariant under a
    rigid motion of the world, which fails if camera-to-world poses are passed where
    world-to-camera are expected), scale handling (scaling the world scales depth
    exactly), loading from a local weights directory and the errors. NOT verified:
    the accuracy of the depth with real weights (e.g. against the simulator's ground
    truth); do that before relying on it (``benchmarks/depth_fidelity.py`` has the
    comparison machinery).
    """

    def __init__(self, model: str | os.PathLike = DEFAULT_DA3_MODEL, *, device: str | None = None,
                 batch_size: int = 4, process_res: int = 504, precision: str = "auto",
                 local_files_only: bool = False, cameras: Sequence[str] | None = None,
                 collinear_tol: float = 1e-2):
        api, _ = _import_da3()
        net = self._load(api.DepthAnything3, model, local_files_only)
        self._setup(net, str(model), "pretrained", device, batch_size, process_res, precision, cameras,
                    collinear_tol)

    @classmethod
    def random_init(cls, preset: str = "da3-small", *, seed: int = 0, **kwargs) -> DepthAnything3:
        """A randomly initialised network (``preset`` from DA3's registry, e.g.
        ``da3-small``): for testing the plumbing only, its depth is meaningless. It
        is described as ``weights: random`` wherever it is recorded."""
        api, _ = _import_da3()
        from depth_anything_3.registry import MODEL_REGISTRY

        if preset not in MODEL_REGISTRY:
            raise InputError(f"unknown Depth Anything 3 preset {preset!r}; known: {sorted(MODEL_REGISTRY)}")
        torch.manual_seed(seed)
        net = api.DepthAnything3(model_name=preset)
        obj = cls.__new__(cls)
        obj._setup(net, preset, "random (testing only: the depth is meaningless)",
                   kwargs.pop("device", None), kwargs.pop("batch_size", 4), kwargs.pop("process_res", 504),
                   kwargs.pop("precision", "auto"), kwargs.pop("cameras", None), kwargs.pop("collinear_tol", 1e-2))
        if kwargs:
            raise TypeError(f"unexpected arguments {sorted(kwargs)}")
        return obj

    @staticmethod
    def _load(api_cls, model, local_files_only: bool):
        text = os.fspath(model)
        path = Path(text).expanduser()
        how = (f"Download the weights where there is internet access (`huggingface-cli download "
               f"{DEFAULT_DA3_MODEL} --local-dir DIR`) and pass DIR, or fill the Hugging Face cache")
        if path.exists():
            if not path.is_dir():
                raise InputError(f"Depth Anything 3 weights: {path} is a file; pass the directory holding "
                                 "config.json and model.safetensors")
            missing = [f for f in ("config.json", "model.safetensors") if not (path / f).is_file()]
            if missing:
                raise InputError(f"Depth Anything 3 weights: {path} lacks {missing}; {how}")
            try:
                return api_cls.from_pretrained(str(path))
            except Exception as e:  # noqa: BLE001 - corrupt or foreign files
                raise InputError(f"Depth Anything 3 weights in {path} could not be loaded: "
                                 f"{type(e).__name__}: {e}") from e
        if not looks_like_hub_id(text):
            raise InputError(f"Depth Anything 3 weights: {text!r} is neither a directory nor a Hugging Face "
                             f"model id like {DEFAULT_DA3_MODEL!r}")
        try:
            return api_cls.from_pretrained(text, local_files_only=local_files_only)
        except Exception as e:  # noqa: BLE001 - hub/network errors come in many types
            raise InputError(f"Depth Anything 3 weights {text!r} are not available here "
                             f"({type(e).__name__}: {str(e).splitlines()[0][:200]}). {how}") from e

    def _setup(self, net, model: str, weights: str, device, batch_size, process_res, precision, cameras,
               collinear_tol) -> None:
        if isinstance(batch_size, bool) or not isinstance(batch_size, int) or batch_size < 1:
            raise InputError(f"DepthAnything3: batch_size must be a positive integer, got {batch_size!r}")
        if isinstance(process_res, bool) or not isinstance(process_res, int) or process_res < 14 \
                or process_res % 14:
            raise InputError(f"DepthAnything3: process_res must be a positive multiple of 14 (the patch size), "
                             f"got {process_res!r}")
        if precision not in ("auto", "fp32", "bf16", "fp16"):
            raise InputError(f"DepthAnything3: precision must be auto, fp32, bf16 or fp16, got {precision!r}")
        if not (isinstance(collinear_tol, (int, float)) and 0 < collinear_tol < 1):
            raise InputError(f"DepthAnything3: collinear_tol must be in (0, 1), got {collinear_tol!r}")
        if device is None:
            device = "cuda" if torch.cuda.is_available() else "cpu"
        try:
            self.device = torch.device(device)
            net = net.to(self.device).eval()
        except (RuntimeError, AssertionError) as e:
            raise InputError(f"DepthAnything3: device {device!r} cannot be used: {e}") from e
        self._api_model = net
        self.model = model
        self.weights = weights
        self.batch_size = batch_size
        self.process_res = process_res
        self.precision = precision
        self.cameras = list(cameras) if cameras is not None else None
        self.collinear_tol = float(collinear_tol)

    # ------------------------------------------------------------------ description
    def describe(self) -> dict[str, Any]:
        try:
            version = importlib.metadata.version("depth-anything-3")
        except importlib.metadata.PackageNotFoundError:
            version = None
        return {
            "kind": "depth_anything_3",
            "package": f"depth-anything-3 {version}",
            "model": self.model,
            "weights": self.weights,
            "process_res": self.process_res,
            "precision": self._autocast_dtype_name(),
            "scale": "Umeyama Sim(3) fit of DA3's predicted camera poses to the dataset's camera poses (metres)",
            "verified": "pipeline verified with random weights only; accuracy with real weights not measured",
        }

    def _autocast_dtype_name(self) -> str:
        if self.precision != "auto":
            return self.precision
        if self.device.type != "cuda":
            return "fp32"
        return "bf16" if torch.cuda.is_bf16_supported() else "fp16"

    # --------------------------------------------------------------------- the source
    def depth(self, views: EpisodeViews) -> dict[str, np.ndarray]:
        cams = self.cameras if self.cameras is not None else sorted(views.cameras)
        missing = [c for c in cams if c not in views.images or c not in views.cameras or c not in views.poses]
        if missing:
            raise InputError(f"{views.name}: camera(s) {missing} lack images, calibration or poses")
        views.num_frames  # noqa: B018 - validates equal frame counts
        for c in cams:
            shape = np.shape(views.images[c])[1:3]
            if tuple(shape) != (views.cameras[c].height, views.cameras[c].width):
                raise InputError(f"{views.name} camera {c!r}: images are {shape[0]}x{shape[1]} but the calibration "
                                 f"is for {views.cameras[c].height}x{views.cameras[c].width}")
        out = self.predict([views.images[c] for c in cams], [views.cameras[c].K for c in cams],
                           [views.poses[c] for c in cams], where=views.name, names=cams)
        return dict(zip(cams, out))

    def predict(self, images: Sequence[np.ndarray], intrinsics: Sequence[np.ndarray],
                poses: Sequence[np.ndarray], *, where: str = "views",
                names: Sequence[str] | None = None) -> list[np.ndarray]:
        """Depth of ``N`` synchronised views over ``T`` timesteps.

        ``images[v]``: ``(T, H_v, W_v, 3)`` uint8 RGB; ``intrinsics[v]``: ``(3, 3)``
        or ``(T, 3, 3)`` for that resolution; ``poses[v]``: ``(T, 4, 4)``
        camera-to-world (OpenCV). Returns ``[(T, H_v, W_v) float32 metres]``.
        """
        names = list(names) if names is not None else [f"view {v}" for v in range(len(images))]
        imgs, Ks, c2w = self._validate(images, intrinsics, poses, where, names)
        T = imgs[0].shape[0]
        check_view_geometry(c2w[:, :, :3, 3], collinear_tol=self.collinear_tol, where=where)
        out = [np.zeros(im.shape[:3], dtype=np.float32) for im in imgs]
        for start in range(0, T, self.batch_size):
            ts = range(start, min(T, start + self.batch_size))
            depth = self._predict_processed(imgs, Ks, c2w, ts)  # (B, N, h, w)
            for v, im in enumerate(imgs):
                H, W = im.shape[1:3]
                for b, t in enumerate(ts):
                    out[v][t] = self._resize_back(depth[b, v], (H, W))
        return out

    def _validate(self, images, intrinsics, poses, where, names):
        n = len(images)
        if not (len(intrinsics) == len(poses) == n == len(names)):
            raise InputError(f"{where}: {n} image streams, {len(intrinsics)} intrinsics, {len(poses)} poses")
        if n < 3:
            raise InputError(f"{where}: Depth Anything 3 needs at least three views with known poses to fix "
                             f"the metric scale; got {n}")
        imgs, Ks, c2w = [], [], []
        T = None
        for v in range(n):
            what = f"{where} {names[v]}"
            im = np.asarray(images[v])
            if im.ndim != 4 or im.shape[-1] != 3 or im.dtype != np.uint8:
                raise InputError(f"{what}: images must be (T, H, W, 3) uint8 RGB; got {im.shape} {im.dtype}")
            T = im.shape[0] if T is None else T
            if im.shape[0] != T or T == 0:
                raise InputError(f"{what}: {im.shape[0]} frames; the views must share T > 0 frames (first has {T})")
            K = np.asarray(intrinsics[v], dtype=np.float64)
            if K.shape == (3, 3):
                K = np.broadcast_to(K, (T, 3, 3))
            if K.shape != (T, 3, 3) or not np.isfinite(K).all():
                raise InputError(f"{what}: intrinsics must be finite (3, 3) or (T, 3, 3); got {K.shape}")
            P = np.asarray(poses[v], dtype=np.float64)
            if P.shape != (T, 4, 4) or not np.isfinite(P).all():
                raise InputError(f"{what}: poses must be finite camera-to-world (T, 4, 4); got {P.shape}")
            R = P[:, :3, :3]
            if (np.abs(P[:, 3] - [0, 0, 0, 1]).max() > 1e-6
                    or np.abs(R @ R.transpose(0, 2, 1) - np.eye(3)).max() > 1e-4):
                raise InputError(f"{what}: poses must be rigid 4x4 transforms (orthonormal rotation, last row "
                                 "0 0 0 1)")
            imgs.append(im)
            Ks.append(K)
            c2w.append(P)
        return imgs, np.stack(Ks, axis=1), np.stack(c2w, axis=1)  # (T, N, 3, 3), (T, N, 4, 4)

    def processed_size(self, height: int, width: int) -> tuple[int, int]:
        """(h, w) the network sees for a ``height`` x ``width`` view: long side
        ``process_res``, both sides the nearest multiple of 14 (DA3's
        ``upper_bound_resize``)."""
        scale = self.process_res / max(height, width)
        return (_nearest_multiple(round(height * scale), 14), _nearest_multiple(round(width * scale), 14))

    def _predict_processed(self, imgs, Ks, c2w, ts) -> np.ndarray:
        """Depth ``(B, N, h, w)`` at the processing size, scaled to the poses' units."""
        api, align_poses_umeyama = _import_da3()
        net = self._api_model
        h, w = self.processed_size(*imgs[0].shape[1:3])
        n = len(imgs)
        batch_imgs, batch_ext, batch_K = [], [], []
        for t in ts:
            views, K_proc = [], []
            for v, im in enumerate(imgs):
                H, W = im.shape[1:3]
                interp = cv2.INTER_AREA if h * w < H * W else cv2.INTER_CUBIC
                views.append(np.ascontiguousarray(cv2.resize(im[t], (w, h), interpolation=interp)))
                K_proc.append(rescale_intrinsics(Ks[t, v], (H, W), (h, w)))
            w2c = np.linalg.inv(c2w[t])  # DA3 wants world-to-camera
            x, ex, K = net.input_processor(views, w2c, np.stack(K_proc), self.process_res, "upper_bound_resize",
                                           num_workers=1, sequential=True)
            if tuple(x.shape[-2:]) != (h, w):  # DA3 must not have resized again
                raise RuntimeError(f"DA3 input processor changed the size to {tuple(x.shape[-2:])}, expected {(h, w)}")
            batch_imgs.append(x)
            batch_ext.append(ex)
            batch_K.append(K)
        x = torch.stack(batch_imgs).to(self.device).float()  # (B, N, 3, h, w)
        ex = torch.stack(batch_ext).to(self.device).float()  # (B, N, 4, 4) world-to-camera
        K = torch.stack(batch_K).to(self.device).float()
        ex_norm = torch.cat([net._normalize_extrinsics(ex[b:b + 1].clone()) for b in range(len(ts))])
        dtype = {"fp32": None, "bf16": torch.bfloat16, "fp16": torch.float16}[self._autocast_dtype_name()]
        with torch.inference_mode():
            if dtype is None:
                out = net.model(x, ex_norm, K, [], False, False, "saddle_balanced")
            else:
                with torch.autocast(device_type=self.device.type, dtype=dtype):
                    out = net.model(x, ex_norm, K, [], False, False, "saddle_balanced")
        depth = out["depth"].float().cpu().numpy().reshape(len(ts), n, h, w)
        pred_ext = out["extrinsics"].float().cpu().numpy()  # (B, N, 3, 4), DA3's frame
        ex_np = ex.cpu().numpy()
        for b in range(len(ts)):
            _, _, scale, _ = align_poses_umeyama(pred_ext[b], ex_np[b], return_aligned=True,
                                                 ransac=n >= 10, random_state=42)
            if not (math.isfinite(scale) and scale > 0):
                raise InputError(f"Depth Anything 3 scale alignment failed at timestep {ts[b]} (scale {scale})")
            depth[b] /= scale
        return depth

    @staticmethod
    def _resize_back(depth: np.ndarray, hw: tuple[int, int]) -> np.ndarray:
        H, W = hw
        d = depth if depth.shape == (H, W) else cv2.resize(depth, (W, H), interpolation=cv2.INTER_LINEAR)
        d = np.where(np.isfinite(d) & (d > 0), d, 0.0)
        return d.astype(np.float32)


class DepthAnything3Metric(DepthAnything3):
    """Depth Anything 3's monocular metric model (``da3metric-large``; default weights
    :data:`DEFAULT_DA3_METRIC_MODEL`), for rigs with fewer than three posed views, where the
    multi-view model's scale fit is not determined. Each view is predicted on its own; DA3's
    metric rule turns the network's output into metres with the view's focal length at the
    processing size: ``metres = (fx + fy) / 2 * output / 300`` (DA3's ``apply_metric_scaling``).
    Loading, devices, precision and batching over time are :class:`DepthAnything3`'s.

    Verified here with random weights only (shapes, the focal rule: halving the focal length
    halves the depth); its accuracy with real weights is not measured. With no calibration at all,
    :meth:`predict_pose_free` is the mode ``qa calibrate`` uses: the scale is then estimated there.
    """

    def describe(self) -> dict[str, Any]:
        d = super().describe()
        d.update(kind="depth_anything_3_metric",
                 scale=f"monocular metric model: metres = mean focal (px, at the processing size) * output / "
                       f"{DA3_METRIC_FOCAL_SCALE:g}")
        return d

    def predict(self, images: Sequence[np.ndarray], intrinsics: Sequence[np.ndarray],
                poses: Sequence[np.ndarray] | None = None, *, where: str = "views",
                names: Sequence[str] | None = None) -> list[np.ndarray]:
        """Depth of each view ``(T, H_v, W_v)`` float32 metres; ``poses`` are not needed."""
        names = list(names) if names is not None else [f"view {v}" for v in range(len(images))]
        out = []
        for v, (im, K) in enumerate(zip(images, intrinsics)):
            im = np.asarray(im)
            if im.ndim != 4 or im.shape[-1] != 3 or im.dtype != np.uint8 or len(im) == 0:
                raise InputError(f"{where} {names[v]}: images must be (T, H, W, 3) uint8 RGB; got {im.shape} "
                                 f"{im.dtype}")
            K = np.asarray(K, dtype=np.float64)
            if K.shape != (3, 3) or not np.isfinite(K).all() or not (K[0, 0] > 0 and K[1, 1] > 0):
                raise InputError(f"{where} {names[v]}: intrinsics must be a finite (3, 3) matrix with fx, fy > 0")
            T, H, W = im.shape[:3]
            h, w = self.processed_size(H, W)
            Kp = rescale_intrinsics(K, (H, W), (h, w))
            focal = 0.5 * (Kp[0, 0] + Kp[1, 1])
            interp = cv2.INTER_AREA if h * w < H * W else cv2.INTER_CUBIC
            depth = np.zeros((T, H, W), np.float32)
            net = self._api_model
            dtype = {"fp32": None, "bf16": torch.bfloat16, "fp16": torch.float16}[self._autocast_dtype_name()]
            for start in range(0, T, self.batch_size):
                ts = range(start, min(T, start + self.batch_size))
                x = torch.stack([net.input_processor(
                    [np.ascontiguousarray(cv2.resize(im[t], (w, h), interpolation=interp))], None, None,
                    self.process_res, "upper_bound_resize", num_workers=1, sequential=True)[0] for t in ts])
                x = x.to(self.device).float()  # (B, 1, 3, h, w)
                with torch.inference_mode():
                    if dtype is None:
                        pred = net.model(x, None, None, [], False, False, "first")
                    else:
                        with torch.autocast(device_type=self.device.type, dtype=dtype):
                            pred = net.model(x, None, None, [], False, False, "first")
                d = pred["depth"].float().cpu().numpy().reshape(len(ts), h, w) * (focal / DA3_METRIC_FOCAL_SCALE)
                for b, t in enumerate(ts):
                    depth[t] = self._resize_back(d[b], (H, W))
            out.append(depth)
        return out

    def predict_pose_free(self, images: np.ndarray, focal_guess: float, *, where: str = "views") -> np.ndarray:
        """Pose-free mode, for a camera with no calibration (``qa calibrate``): depth ``(T, H, W)``
        of one view's frames from a guessed focal length (px, at the images' size) and the image
        centre, nothing else. Its scale is the metric rule's with that guess, so it is off by the
        guess's error and the model's own; the caller estimates the scale with the pose (a
        similarity fit) and reports it. Depth only, without the scale, is what this mode promises."""
        if not (isinstance(focal_guess, (int, float)) and math.isfinite(focal_guess) and focal_guess > 0):
            raise InputError(f"{where}: focal_guess must be a positive number of pixels, got {focal_guess!r}")
        H, W = np.shape(images)[1:3]
        K = np.array([[focal_guess, 0.0, (W - 1) / 2.0], [0.0, focal_guess, (H - 1) / 2.0], [0.0, 0.0, 1.0]])
        return self.predict([images], [K], where=where)[0]

    def depth(self, views: EpisodeViews) -> dict[str, np.ndarray]:
        cams = self.cameras if self.cameras is not None else sorted(views.cameras)
        missing = [c for c in cams if c not in views.images or c not in views.cameras]
        if missing:
            raise InputError(f"{views.name}: camera(s) {missing} lack images or calibration")
        out = self.predict([views.images[c] for c in cams], [views.cameras[c].K for c in cams],
                           where=views.name, names=cams)
        return dict(zip(cams, out))


# --------------------------------------------------------------------------- the recipe's da3 source


def uses_monocular(num_cameras: int) -> bool:
    """DA3's multi-view scale fit needs three posed views; fewer use the monocular metric model."""
    return num_cameras < 3


def da3_model(section, recipe_file: str, monocular: bool) -> str:
    """The model a recipe's ``depth:`` section names: a local directory (relative to the recipe)
    or a hub id; the default DA3 model otherwise."""
    value = section.monocular_model if monocular else section.model
    field = "depth.monocular_model" if monocular else "depth.model"
    if value is None:
        return DEFAULT_DA3_METRIC_MODEL if monocular else DEFAULT_DA3_MODEL
    path = Path(os.path.expandvars(os.path.expanduser(value)))
    if not path.is_absolute() and recipe_file:
        local = Path(recipe_file).parent / path
        if local.exists() or not looks_like_hub_id(value):
            path = local
    if path.exists():
        return str(path)
    if looks_like_hub_id(value) and not value.startswith(("/", ".")):
        return value
    raise InputError(f"{recipe_file or '<recipe>'}: {field}: the Depth Anything 3 model directory {path} does not "
                     "exist (give a directory holding config.json and model.safetensors, or a Hugging Face "
                     "model id such as depth-anything/DA3-BASE)")


def check_da3_inputs(section, recipe_file: str, num_cameras: int) -> str:
    """The model the build will load (an :class:`InputError` now if its directory is missing)."""
    return da3_model(section, recipe_file, uses_monocular(num_cameras))


def make_da3_source(section, recipe_file: str, num_cameras: int, *, local_files_only: bool = False):
    """DA3 as a recipe's depth source: posed multi-view with three cameras or more, else monocular metric."""
    cls = DepthAnything3Metric if uses_monocular(num_cameras) else DepthAnything3
    return cls(check_da3_inputs(section, recipe_file, num_cameras), device=section.device,
               batch_size=section.batch_size, process_res=section.process_res, local_files_only=local_files_only)
