"""The depth colour codec: metric depth <-> RGB (Vision Banana; ``docs/dataset-format.md``).

A power transform ``f(d) = 1 - (1 - d / (lam c)) ** (lam + 1)`` squashes metres into
``[0, 1)``, and ``7 f`` walks the RGB cube corners black, red, yellow, green, cyan, blue,
magenta, white. Decoding projects a colour onto the nearest segment of the walk (so colours
pushed off it still decode to a nearby depth) and inverts both steps. Black is reserved for
invalid depth (0, NaN, inf), so valid depth is clamped to the depths of codes 1 and 1784.
Every function takes numpy arrays or torch tensors and returns the same kind (any device,
differentiable through ``encode`` and ``decode``)::

    codec = DepthCodec.preset("manipulation")         # the default
    frames = codec.encode_uint8(depth_m)              # (T, H, W, 3) uint8, for a video encoder
    depth_back = codec.decode(frames)                 # (T, H, W) float32 metres, 0 = invalid"""

from __future__ import annotations

import math
import sys
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from imac_data.core.metric_depth import depth_from_millimetres, dtype_name, is_torch
from imac_data.errors import InputError
from imac_data.metadata import imac_block

__all__ = [
    "CODEC_ID",
    "CORNERS",
    "CORNER_NAMES",
    "N_CODES",
    "PRESETS",
    "DepthCodec",
    "path_position",
    "walk_colour",
]

CODEC_ID = "vision_banana_rgb_walk"
CODEC_VERSION = 1

CORNER_NAMES = ("black", "red", "yellow", "green", "cyan", "blue", "magenta", "white")
CORNERS = np.array(
    [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 1, 1], [0, 0, 1], [1, 0, 1], [1, 1, 1]],
    dtype=np.float64,
)
N_SEGMENTS = 7
CODE_LEVELS = 255  # 8-bit steps per segment
N_CODES = N_SEGMENTS * CODE_LEVELS  # 1785: code 0 = black (invalid), 1785 = white (unused)

# Clamp range of the walk position s, in [0, 7]: codes 1 and N_CODES - 1.
_S_MIN = 1.0 / CODE_LEVELS
_S_MAX = N_SEGMENTS - _S_MIN

PRESETS: dict[str, tuple[float, float]] = {
    # The public iMaC release's values: fine steps up to ~2 m, saturates at 4.0 m.
    "manipulation": (-500.0, 0.53),
    # The paper's (and Vision Banana's) values: useful to tens of metres.
    "general": (-3.0, 10.0 / 3.0),
}
DEFAULT_PRESET = "manipulation"


# --------------------------------------------------------------------------- walk tables
def _walk_tables() -> tuple[list[int], list[float], list[int], list[int], list[int]]:
    """Per-segment constants derived from CORNERS, so the walk is defined in one place.

    Segment j moves channel ``MOVING[j]`` by ``SIGN[j]`` (+1 or -1). With the six
    planes ``dev = [r, g, b, 1 - r, 1 - g, 1 - b]`` of a colour inside the cube:

    * the fraction along segment j is ``dev[T_IDX[j]]``;
    * the squared distance to segment j is ``dev[F1_IDX[j]]**2 + dev[F2_IDX[j]]**2``
      (how far its two fixed channels are from their values, 0 or 1).
    """
    start = CORNERS[:-1]
    step = np.diff(CORNERS, axis=0)
    assert np.all(np.abs(step).sum(axis=1) == 1), "each segment must move exactly one channel"
    assert not CORNERS[0].any(), "the walk must start at black (= invalid)"
    moving, sign, t_idx, f1_idx, f2_idx = [], [], [], [], []
    for j in range(N_SEGMENTS):
        ch = int(np.flatnonzero(step[j])[0])
        moving.append(ch)
        sign.append(float(step[j, ch]))
        t_idx.append(ch if step[j, ch] > 0 else 3 + ch)
        fixed = [other for other in range(3) if other != ch]
        f1_idx.append(fixed[0] + 3 * int(start[j, fixed[0]]))
        f2_idx.append(fixed[1] + 3 * int(start[j, fixed[1]]))
    return moving, sign, t_idx, f1_idx, f2_idx


_MOVING, _SIGN, _T_IDX, _F1_IDX, _F2_IDX = _walk_tables()


# ------------------------------------------------------------------------------ backends
class _Backend:
    """The few operations where numpy and torch differ; the rest is ``self.xp``."""

    def __init__(self, xp: Any):
        self.xp = xp
        self.is_torch = xp is not np

    def cast(self, x, dtype):
        return x.to(dtype) if self.is_torch else x.astype(dtype)

    def to_uint8(self, x):
        """Round half to even and cast (values already in [0, 255])."""
        if self.is_torch:
            return self.xp.round(x).to(self.xp.uint8)
        return np.rint(x).astype(np.uint8)


_NUMPY = _Backend(np)


def _backend(x) -> _Backend:
    return _Backend(sys.modules["torch"]) if is_torch(x) else _NUMPY


def _work_float(bk: _Backend, x):
    """``x`` as a float array of at least float32 precision."""
    if bk.is_torch:
        torch = bk.xp
        return x if x.dtype in (torch.float32, torch.float64) else x.to(torch.float32)
    return x if x.dtype in (np.float32, np.float64) else x.astype(np.float32)


# ---------------------------------------------------------------------------- walk core
def _walk_to_rgb(bk: _Backend, s, r):
    """Walk position -> colour (..., 3). Takes both ``s`` and ``r = 7 - s`` (each
    computed without cancellation): the first half of the walk reads ``s``, the
    second half ``r``, so float32 keeps full precision at both ends.

    Each channel is piecewise linear in s: ``sum_j SIGN[j] * clip(s - j, 0, 1)``
    over the segments j that move it (the walk starts at black).
    """
    xp = bk.xp
    channels: list[Any] = [0.0, 0.0, 0.0]
    for j in range(N_SEGMENTS):
        along = s - j if j < 0.5 * N_SEGMENTS else (N_SEGMENTS - j) - r
        channels[_MOVING[j]] = channels[_MOVING[j]] + _SIGN[j] * xp.clip(along, 0.0, 1.0)
    return xp.stack(channels, axis=-1)


def _rgb_to_walk(bk: _Backend, planes, with_distance: bool = False):
    """Colour planes [r, g, b] inside the cube -> (k, t): segment index (float) and
    fraction along it of the nearest point on the walk (ties: the earlier segment);
    with ``with_distance`` also the squared distance to that point.

    A running minimum over the 7 segments: elementwise ops only, which beats
    stacking the distances and an argmin on both backends.
    """
    xp = bk.xp
    dev = list(planes) + [1.0 - p for p in planes]
    sq = [v * v for v in dev]
    best = sq[_F1_IDX[0]] + sq[_F2_IDX[0]]
    k = xp.zeros_like(best)
    t = dev[_T_IDX[0]]
    for j in range(1, N_SEGMENTS):
        dist2 = sq[_F1_IDX[j]] + sq[_F2_IDX[j]]
        closer = dist2 < best
        best = xp.where(closer, dist2, best)
        k = xp.where(closer, float(j), k)
        t = xp.where(closer, dev[_T_IDX[j]], t)
    return (k, t, best) if with_distance else (k, t)


def _colour_planes(bk: _Backend, rgb, name: str, channel_axis: int) -> list:
    """Validated colours -> three float planes (r, g, b) in [0, 1], each (...)."""
    if not bk.is_torch:
        rgb = np.asarray(rgb)
    if rgb.ndim == 0:
        raise InputError(f"{name}: colours must have a channel axis of size 3; got a scalar")
    if channel_axis not in (-1, rgb.ndim - 1):
        rgb = bk.xp.moveaxis(rgb, channel_axis, -1)
    if rgb.shape[-1] != 3:
        raise InputError(
            f"{name}: colours must have 3 channels on axis {channel_axis}; got shape {tuple(rgb.shape)}"
        )
    xp = bk.xp
    if rgb.dtype == xp.uint8:
        return [bk.cast(rgb[..., ch], xp.float32) / 255.0 for ch in range(3)]
    if not (rgb.dtype.is_floating_point if bk.is_torch else rgb.dtype.kind == "f"):
        raise InputError(f"{name}: colours must be uint8 (0..255) or float (0..1); got {dtype_name(rgb)}")
    rgb = _work_float(bk, rgb)
    return [xp.clip(rgb[..., ch], 0.0, 1.0) for ch in range(3)]


def path_position(rgb, *, channel_axis: int = -1, name: str = "colours"):
    """Position ``s`` in ``[0, 7]`` of each colour's projection on the walk (0 = black,
    ``j`` = corner ``CORNER_NAMES[j]``); independent of the codec parameters.

    ``rgb``: uint8 (0..255) or float (``[0, 1]``) colours, channels on ``channel_axis``.
    """
    bk = _backend(rgb)
    k, t = _rgb_to_walk(bk, _colour_planes(bk, rgb, name, channel_axis))
    return k + t


def walk_colour(s):
    """The colour ``(..., 3)`` in ``[0, 1]`` at walk position ``s`` (clipped to ``[0, 7]``): the
    inverse of :func:`path_position` on the walk; independent of the codec parameters."""
    bk = _backend(s)
    s = bk.xp.clip(_work_float(bk, s), 0.0, float(N_SEGMENTS))
    return _walk_to_rgb(bk, s, N_SEGMENTS - s)


def walk_distance(rgb, *, channel_axis: int = -1, name: str = "colours"):
    """Euclidean distance of each colour to the codec's walk through the RGB cube, in
    [0, 1] colour units (0 for an encoded depth colour; a lossless stream stays within
    about 1/255, rounding). What a check uses to tell depth frames from other images."""
    bk = _backend(rgb)
    _, _, d2 = _rgb_to_walk(bk, _colour_planes(bk, rgb, name, channel_axis), with_distance=True)
    return bk.xp.sqrt(d2)


# --------------------------------------------------------------------------------- codec
def _as_real(value, field: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise InputError(f"depth codec {field} must be a real number; got {value!r}")
    value = float(value)
    if not math.isfinite(value):
        raise InputError(f"depth codec {field} must be finite; got {value!r}")
    return value


@dataclass(frozen=True)
class DepthCodec:
    """Depth colour codec with power-transform parameters ``lam < -1`` and ``c > 0``.

    The default is the ``manipulation`` preset; see :data:`PRESETS` and the module
    docstring for the definition, the invalid/black convention and the range.
    """

    lam: float = PRESETS[DEFAULT_PRESET][0]
    c: float = PRESETS[DEFAULT_PRESET][1]

    def __post_init__(self):
        lam = _as_real(self.lam, "lam")
        c = _as_real(self.c, "c")
        if not lam < -1.0:
            raise InputError(
                f"depth codec lam must be < -1 (so f maps [0, inf) onto [0, 1)); got lam={lam}"
            )
        if not c > 0.0:
            raise InputError(f"depth codec c must be > 0 (a depth scale in metres); got c={c}")
        # Plain Python floats: numpy scalars would silently upcast float32 arrays.
        object.__setattr__(self, "lam", lam)
        object.__setattr__(self, "c", c)

    # ---------------------------------------------------------------- construction
    @classmethod
    def preset(cls, name: str = DEFAULT_PRESET) -> DepthCodec:
        """``"manipulation"`` (lam=-500, c=0.53; default) or ``"general"`` (lam=-3, c=10/3)."""
        if name not in PRESETS:
            raise InputError(f"unknown depth codec preset {name!r}; known presets: {sorted(PRESETS)}")
        lam, c = PRESETS[name]
        return cls(lam, c)

    @property
    def preset_name(self) -> str | None:
        """The preset these parameters equal, or None for custom parameters."""
        for name, params in PRESETS.items():
            if (self.lam, self.c) == params:
                return name
        return None

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready description, enough to decode a stream without this code."""
        return {
            "codec": CODEC_ID,
            "version": CODEC_VERSION,
            "preset": self.preset_name,
            "lam": self.lam,
            "c": self.c,
            "transform": "f(d) = 1 - (1 - d/(lam*c))**(lam+1), d in metres",
            "path": list(CORNER_NAMES),
            "code_levels": CODE_LEVELS,
            "invalid": "black (0, 0, 0); valid depth is clamped to [min_depth, max_depth]",
            "min_depth": self.min_depth,
            "max_depth": self.max_depth,
        }

    @classmethod
    def from_dict(cls, entry: Mapping[str, Any], *, where: str = "depth codec entrydata") -> DepthCodec:
        """Inverse of :meth:`to_dict` (informational keys are checked, not needed)."""
        if not isinstance(entry, Mapping):
            raise InputError(f"{where}: expected a mapping, got {type(entry).__name__}")
        codec = entry.get("codec", CODEC_ID)
        if codec != CODEC_ID:
            raise InputError(f"{where}: codec is {codec!r}, this code decodes {CODEC_ID!r}")
        version = entry.get("version", CODEC_VERSION)
        if version != CODEC_VERSION:
            raise InputError(f"{where}: codec version {version!r} is not supported (expected {CODEC_VERSION})")
        if "path" in entry and list(entry["path"]) != list(CORNER_NAMES):
            raise InputError(f"{where}: path {entry['path']!r} differs from this codec's {list(CORNER_NAMES)}")
        if "code_levels" in entry and entry["code_levels"] != CODE_LEVELS:
            raise InputError(f"{where}: code_levels {entry['code_levels']!r} is not {CODE_LEVELS}")
        missing = [key for key in ("lam", "c") if key not in entry]
        if missing:
            raise InputError(f"{where}: missing key(s) {missing}")
        return cls(entry["lam"], entry["c"])

    # ------------------------------------------------------- scalar math (float64)
    def transform(self, depth):
        """f(d) in float64 numpy, straight from the definition (for reference and plots)."""
        d = np.asarray(depth, dtype=np.float64)
        return 1.0 - (1.0 - d / (self.lam * self.c)) ** (self.lam + 1.0)

    def inverse_transform(self, f):
        """d(f) in float64 numpy, straight from the definition."""
        f = np.asarray(f, dtype=np.float64)
        return self.lam * self.c * (1.0 - (1.0 - f) ** (1.0 / (self.lam + 1.0)))

    def depth_of_code(self, code):
        """Depth (metres, float64) at 8-bit code position ``code`` along the walk (0..1785)."""
        return self.inverse_transform(np.asarray(code, dtype=np.float64) / N_CODES)

    @property
    def min_depth(self) -> float:
        """Smallest encodable depth: code 1, the first colour after black."""
        return float(self.depth_of_code(1))

    @property
    def max_depth(self) -> float:
        """Largest encodable depth: code 1784, the last colour before white."""
        return float(self.depth_of_code(N_CODES - 1))

    def quantisation_step(self, depth):
        """Metres per 8-bit code step at ``depth`` (float64): ``1 / (1785 f'(d))``.

        One code step changes one channel of the colour by one LSB. Rounding to the
        nearest code errs by at most half the step at the larger of the true and the
        decoded depth (the step grows with depth).
        """
        d = np.asarray(depth, dtype=np.float64)
        lam, c = self.lam, self.c
        slope = (lam + 1.0) / (lam * c) * (1.0 - d / (lam * c)) ** lam
        return 1.0 / (N_CODES * slope)

    # ------------------------------------------------------------------- encoding
    def _check_depth(self, bk: _Backend, depth, name: str):
        if bk.is_torch:
            if not depth.dtype.is_floating_point:
                raise _integer_depth_error(name, depth)
        else:
            depth = np.asarray(depth)
            if depth.dtype.kind != "f":
                raise _integer_depth_error(name, depth)
        depth = _work_float(bk, depth)
        negative = (depth < 0) & bk.xp.isfinite(depth)
        if bool(negative.any()):
            count = int(negative.sum())
            lowest = float(depth[negative].min())
            raise InputError(
                f"{name}: {count} negative depth value(s) (lowest {lowest:.6g} m); depth must be "
                "metres >= 0, with 0, NaN or inf marking invalid pixels"
            )
        return depth

    def _encode_float(self, bk: _Backend, depth):
        xp = bk.xp
        valid = xp.isfinite(depth) & (depth > 0)
        d = xp.clip(xp.where(valid, depth, 1.0), self.min_depth, self.max_depth)
        # 1 - f = (1 + d / (|lam| c)) ** (lam + 1) = exp(L)
        log_u = (self.lam + 1.0) * xp.log1p(d / (-self.lam * self.c))
        s = -N_SEGMENTS * xp.expm1(log_u)  # walk position 7 f, precise near 0
        r = N_SEGMENTS * xp.exp(log_u)  # 7 - s, precise near s = 7
        rgb = _walk_to_rgb(bk, s, r)
        return xp.where(valid[..., None], rgb, 0.0)

    def encode(self, depth, *, channel_axis: int = -1, name: str = "depth"):
        """Depth in metres (any shape ``S``, float) -> colours ``S + (3,)`` in [0, 1].

        numpy in, numpy out; torch in, torch out (same device). Invalid depth (0,
        NaN, inf) -> black. Raises :class:`InputError` for integer or negative
        depth. ``name`` is used in error messages (e.g. the episode and camera).
        """
        bk = _backend(depth)
        depth = self._check_depth(bk, depth, name)
        rgb = self._encode_float(bk, depth)
        if channel_axis not in (-1, rgb.ndim - 1):
            rgb = bk.xp.moveaxis(rgb, -1, channel_axis)
        return rgb

    def encode_uint8(self, depth, *, channel_axis: int = -1, name: str = "depth"):
        """As :meth:`encode`, rounded to uint8 colours (0..255): frames for a video encoder.

        float32 numpy depth that came from whole millimetres (``depth_from_millimetres``:
        every recorded depth stream) is looked up in a table of this very function over
        the 65,536 uint16 millimetre values, which gives the same bytes (each value is
        computed elementwise either way; ``tests/test_depth_codec.py`` checks every
        table entry) at about a quarter of the cost; other values are computed.
        """
        bk = _backend(depth)
        if not bk.is_torch and np.asarray(depth).dtype == np.float32:
            rgb = self._encode_uint8_float32(self._check_depth(bk, depth, name))
            return rgb if channel_axis in (-1, rgb.ndim - 1) else np.moveaxis(rgb, -1, channel_axis)
        rgb = self.encode(depth, channel_axis=channel_axis, name=name)
        return bk.to_uint8(rgb * 255.0)

    def _encode_uint8_computed(self, depth: np.ndarray) -> np.ndarray:
        return _NUMPY.to_uint8(self._encode_float(_NUMPY, depth) * 255.0)

    def _encode_uint8_float32(self, depth: np.ndarray) -> np.ndarray:
        metres, colours = _millimetre_table(self)
        with np.errstate(invalid="ignore"):  # NaN / inf cast to some integer, clipped, and then fail the check
            mm = np.rint(depth * np.float32(1000.0)).astype(np.intp)
        np.clip(mm, 0, len(metres) - 1, out=mm)
        on_grid = np.take(metres, mm) == depth
        rgb = np.take(colours, mm, axis=0)
        if not on_grid.all():
            off = ~on_grid
            rgb[off] = self._encode_uint8_computed(depth[off])
        return rgb

    # ------------------------------------------------------------------- decoding
    def decode(self, rgb, *, invalid_codes: float = 0.5, channel_axis: int = -1, name: str = "depth colours"):
        """Colours (uint8 0..255, or float in [0, 1]; channels on ``channel_axis``) -> depth.

        Returns metres with the colour's shape minus the channel axis: float32
        (float64 for float64 input), 0 where invalid. Colours off the walk decode
        via their nearest point on it; a colour whose projection is within
        ``invalid_codes`` 8-bit codes of black is invalid. numpy in, numpy out;
        torch in, torch out (same device, differentiable w.r.t. float colours).
        """
        bk = _backend(rgb)
        planes = _colour_planes(bk, rgb, name, channel_axis)
        if not invalid_codes >= 0:
            raise InputError(f"{name}: invalid_codes must be >= 0; got {invalid_codes!r}")
        xp = bk.xp
        k, t = _rgb_to_walk(bk, planes)
        s = k + t
        valid = s >= invalid_codes / CODE_LEVELS  # False for NaN colours as well
        r = xp.clip((N_SEGMENTS - k) - t, _S_MIN, _S_MAX)  # 7 - s without cancellation
        s = xp.clip(s, _S_MIN, _S_MAX)
        # log(1 - f), with f = s / 7
        log_u = xp.where(s < 0.5 * N_SEGMENTS, xp.log1p(-s / N_SEGMENTS), xp.log(r / N_SEGMENTS))
        depth = (-self.lam * self.c) * xp.expm1(log_u / (self.lam + 1.0))
        return xp.where(valid, depth, 0.0)


_MILLIMETRE_TABLES: dict[tuple[float, float], tuple[np.ndarray, np.ndarray]] = {}


def _millimetre_table(codec: DepthCodec) -> tuple[np.ndarray, np.ndarray]:
    """``(metres (65536,) float32, colours (65536, 3) uint8)``: every uint16 millimetre
    depth as :func:`depth_from_millimetres` converts it, and its computed uint8 colour."""
    key = (codec.lam, codec.c)
    table = _MILLIMETRE_TABLES.get(key)  # (thread-safe: no check-then-read)
    if table is None:
        metres = depth_from_millimetres(np.arange(1 << 16, dtype=np.uint16))
        table = _MILLIMETRE_TABLES[key] = (metres, codec._encode_uint8_computed(metres))
    return table


def _integer_depth_error(name: str, depth) -> InputError:
    return InputError(
        f"{name}: depth must be float metres; got {dtype_name(depth)}. Integer depth is usually "
        "millimetres from a depth sensor: convert it with imac_data.core.metric_depth.depth_from_millimetres()"
    )


__all__ += ["depth_codec_of", "walk_distance"]


def depth_codec_of(meta) -> DepthCodec:
    """The codec of a dataset's depth streams, from its metadata: ``ds.meta``, the dataset's
    root or its ``dataset_info`` dict (:mod:`imac_data.metadata`). Decode a loaded frame with
    ``depth_codec_of(ds.meta).decode(item[key], channel_axis=-3)`` (LeRobot returns float
    ``(3, H, W)`` colours in [0, 1]; the result is metres, 0 = invalid)."""
    depth = imac_block(meta).get("depth")
    codec = depth.get("codec") if isinstance(depth, Mapping) else None
    if codec is None:
        raise InputError("meta/info.json has no imac.depth.codec: the dataset has no depth streams written by imac")
    return DepthCodec.from_dict(codec, where="meta/info.json imac.depth.codec")


def _as_numpy_depth(depth, name: str) -> np.ndarray:
    if is_torch(depth):
        depth = depth.detach().cpu().numpy()
    depth = np.asarray(depth)
    if depth.ndim != 3:
        raise InputError(f"{name}: depth must be (T, H, W) metres; got shape {depth.shape}")
    if depth.dtype.kind != "f":
        raise _integer_depth_error(name, depth)
    return depth
