"""LeRobot's native depth maps (LeRobot 0.6): metric depth as 12-bit codes in a ``gray12le`` video.

The quantiser and its parameters, as LeRobot 0.6.1's ``datasets/depth_utils.py`` defines them
(log or linear between ``depth_min`` and ``depth_max`` metres), read from and written to a
feature's ``info`` block, checked. Code 0 means invalid here (``docs/lerobot.md``, "Native
depth maps"). No LeRobot import: the formulas are re-implemented and tested against LeRobot's.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from imac_data.errors import InputError

__all__ = ["QMAX", "PIX_FMT", "DepthMapParams", "depth_marker", "is_depth_map", "params_of_feature"]

QMAX = 4095  # 12-bit codes 0..4095 (LeRobot's DEPTH_QMAX)
PIX_FMT = "gray12le"
UNITS = ("m", "mm")  # LeRobot's depth_unit values: the unit of the raw frames (and of the stats)


@dataclass(frozen=True)
class DepthMapParams:
    """The quantiser of one depth-map feature; metres. Defaults: LeRobot 0.6's."""

    depth_min: float = 0.01
    depth_max: float = 10.0
    shift: float = 3.5
    use_log: bool = True

    def problem(self) -> str | None:
        """What is wrong with these parameters (None: nothing), in the feature's key names."""
        for name in ("depth_min", "depth_max", "shift"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float, np.floating, np.integer)) or not math.isfinite(v):
                return f"video.{name} must be a finite number, got {v!r}"
        if not isinstance(self.use_log, (bool, np.bool_)):
            return f"video.use_log must be true or false, got {self.use_log!r}"
        if not 0 <= self.depth_min < self.depth_max:
            return f"needs 0 <= video.depth_min < video.depth_max, got {self.depth_min} and {self.depth_max}"
        if self.use_log and not self.depth_min + self.shift > 0:
            return (f"log quantisation needs video.depth_min + video.shift > 0, got {self.depth_min} + "
                    f"{self.shift}")
        return None

    def check(self, where: str) -> DepthMapParams:
        problem = self.problem()
        if problem:
            raise InputError(f"{where}: {problem}")
        return self

    def info(self) -> dict:
        """The parameters as a feature's ``info`` keys (LeRobot's ``video.<name>``)."""
        return {"video.depth_min": float(self.depth_min), "video.depth_max": float(self.depth_max),
                "video.shift": float(self.shift), "video.use_log": bool(self.use_log)}

    def code_values(self) -> np.ndarray:
        """``(4096,)`` float64 metres of every code, as LeRobot's ``dequantize_depth`` reads
        them (code 0 = ``depth_min``; clipped to ``[depth_min, depth_max]``)."""
        c = np.arange(QMAX + 1, dtype=np.float64)
        if self.use_log:
            lo, hi = math.log(self.depth_min + self.shift), math.log(self.depth_max + self.shift)
            d = np.exp(c * ((hi - lo) / QMAX) + lo) - self.shift
        else:
            d = c * ((self.depth_max - self.depth_min) / QMAX) + self.depth_min
        return np.clip(d, self.depth_min, self.depth_max)

    def dequantize(self, codes: np.ndarray) -> np.ndarray:
        """float32 metres of 12-bit ``codes``; code 0 (depth at or below ``depth_min``, or
        invalid) gives 0 = invalid."""
        codes = np.asarray(codes)
        if codes.dtype.kind not in "ui" or (codes.size and (codes.min() < 0 or codes.max() > QMAX)):
            raise InputError(f"depth-map codes must be integers 0..{QMAX}, got {codes.dtype} up to "
                             f"{codes.max() if codes.size else None}")
        table = self.code_values().astype(np.float32)
        table[0] = 0.0
        return table[codes]

    def quantize(self, depth_m: np.ndarray) -> np.ndarray:
        """uint16 codes of float metres, with the float32 arithmetic of LeRobot's
        ``quantize_depth`` (the same codes), except that code 0 is kept for invalid depth (0,
        NaN, +-inf, negative): valid depth that LeRobot would write as 0 (less than half a step
        above ``depth_min``, or nearer) gets code 1, so that a reader of either kind can tell
        invalid pixels from valid ones (LeRobot reads code 0 as ``depth_min``; it maps NaN by an
        unchecked cast and +inf to 4095)."""
        d = np.asarray(depth_m).astype(np.float32)
        dmin, dmax, s = np.float32(self.depth_min), np.float32(self.depth_max), np.float32(self.shift)
        with np.errstate(invalid="ignore", divide="ignore"):
            if self.use_log:
                lo, hi = math.log(float(dmin + s)), math.log(float(dmax + s))
                norm = (np.log(d + s) - lo) / (hi - lo)
            else:
                norm = (d - dmin) / (dmax - dmin)
            q = np.rint(norm * QMAX)
        valid = np.isfinite(d) & (d > 0)
        q = q.clip(0, QMAX)
        q[valid & (q < 1)] = 1
        q[~valid] = 0
        return q.astype(np.uint16)

    def step(self, depth_m: float) -> float:
        """The quantiser's step (metres) at ``depth_m``."""
        if self.use_log:
            span = math.log((self.depth_max + self.shift) / (self.depth_min + self.shift))
            return (depth_m + self.shift) * span / QMAX
        return (self.depth_max - self.depth_min) / QMAX


# the three places a depth-map marker has lived: LeRobot >= 0.6.0's canonical one, the key every
# LeRobot <= 0.5 video feature carries (always false there), and v2.x metadata's video_info
MARKERS = (("info", "is_depth_map"), ("info", "video.is_depth_map"), ("video_info", "video.is_depth_map"))


def depth_marker(feature: Mapping) -> bool | None:
    """The feature's depth-map flag, whichever of :data:`MARKERS` carries it (None: none
    does). Markers that disagree raise ``ValueError``: LeRobot 0.6.1 and its head read them
    differently."""
    marks = {}
    for block, key in MARKERS:
        holder = feature.get(block)
        if isinstance(holder, Mapping) and holder.get(key) is not None:
            marks[f"{block}[{key!r}]"] = holder[key]
    bad = {k: v for k, v in marks.items() if not isinstance(v, (bool, np.bool_))}
    if bad:
        raise ValueError(f"depth-map marker(s) {bad} must be true or false")
    if len(set(marks.values())) > 1:
        raise ValueError(f"conflicting depth-map markers {marks}")
    return next(iter(marks.values())) if marks else None


def is_depth_map(feature: Mapping) -> bool:
    """True if any marker flags ``feature`` as a depth map (conflicts raise ``ValueError``)."""
    return bool(depth_marker(feature))


def params_of_feature(feature: Mapping, where: str) -> DepthMapParams:
    """The quantiser of a native depth-map ``feature`` (a ``meta/info.json`` feature dict),
    checked. :class:`InputError` starting with ``where`` (the dataset and the key) for
    anything LeRobot would default silently or mis-decode."""
    try:
        marked = depth_marker(feature)
    except ValueError as e:
        raise InputError(f"{where}: {e}") from None
    if not marked:
        raise InputError(f"{where} is not flagged as a depth map (no info.is_depth_map: true)")
    if feature.get("dtype") != "video":
        raise InputError(f"{where}: dtype {feature.get('dtype')!r}; a depth map is a 'video' feature")
    shape = list(feature.get("shape") or [])
    if len(shape) != 3 or shape[2] != 1:
        raise InputError(f"{where}: shape {shape}; a depth map is (height, width, 1)")
    info = feature.get("info") if isinstance(feature.get("info"), Mapping) else {}
    missing = [k for k in ("video.depth_min", "video.depth_max", "video.shift", "video.use_log")
               if info.get(k) is None]
    if missing:
        raise InputError(f"{where}: info lacks {missing}; refusing to guess the quantiser (LeRobot would use its "
                         "defaults, which need not be what encoded the video)")
    if info.get("video.pix_fmt") != PIX_FMT:
        raise InputError(f"{where}: video.pix_fmt {info.get('video.pix_fmt')!r}; a depth map is {PIX_FMT}")
    if info.get("depth_unit") is not None and info.get("depth_unit") not in UNITS:
        raise InputError(f"{where}: depth_unit {info.get('depth_unit')!r}; LeRobot writes 'm' or 'mm'")
    params = DepthMapParams(info["video.depth_min"], info["video.depth_max"], info["video.shift"],
                            info["video.use_log"])
    return params.check(where)
