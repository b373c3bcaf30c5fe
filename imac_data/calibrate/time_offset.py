"""A camera's constant time offset to the joint states, for ``qa calibrate`` and the build.

USB cameras are often out of step with the joint states: frame ``k`` of a camera shows the robot
at the joint states' time ``t_k + offset`` (negative: the camera lags). Both the estimate and the
build read the joint states between frames by Catmull-Rom interpolation, clamped at the episode's ends
(:func:`joints_at`).

The estimate (:func:`search_offset`) is a profile: at each trial offset the camera's depth fit
(:mod:`.register`) is re-run from the pose found at offset 0, with the robot posed at the joint
states of ``t + offset``, and scored by a truncated quadratic cost of the point-to-plane residuals
(:func:`fit_cost`). Whole frames over the search window first, then a golden-section search within
one frame of the best. The curve's sharpness is the confidence: how much the cost rises one frame
either side of the best (``rise``), and the cost and inlier share at offset 0 against the best.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from imac_data.calibrate.register import Fit, fit_pose
from imac_data.calibrate.surface import lift
from imac_data.core.motion import joints_at

__all__ = ["joints_at", "episode_joints_at", "fit_cost", "OffsetSearch", "search_offset", "timing_refusal",
           "COST_CUT", "MIN_RISE"]

COST_CUT = 0.015  # metres: residuals beyond count as a miss in the cost (a frame of arm motion is ~5-15 mm)
MIN_RISE = 0.02  # the cost must rise this much (relative) one frame either side, or the offset is not observable
_GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0


def episode_joints_at(joints: Mapping[str, np.ndarray], refs: Sequence[tuple[str, int]], shift: float) -> np.ndarray:
    """``(len(refs), D)``: the joint vectors of frames ``refs`` ((episode, frame) pairs, episodes
    contiguous) shifted by ``shift`` frames, interpolated per episode (:func:`joints_at`)."""
    parts = []
    for ep in dict.fromkeys(e for e, _ in refs):
        ts = np.array([t for e, t in refs if e == ep], dtype=np.float64)
        parts.append(joints_at(joints[ep], ts + shift))
    return np.concatenate(parts)


def fit_cost(obs: Sequence[np.ndarray], A: np.ndarray, X: np.ndarray, targets, focal: float, scale: float,
             cut: float = COST_CUT) -> float:
    """Mean truncated quadratic ``min((r / cut)^2, 1)`` of the point-to-plane residuals ``r`` of every
    observed point (a point with no target point within ``cut`` counts 1): 0 = a perfect fit."""
    total, n = 0.0, 0
    for o, Ai, tg in zip(obs, A, targets):
        if not len(o):
            continue
        M = Ai @ X
        w = lift(o, focal, scale) @ M[:3, :3].T + M[:3, 3]
        d, j = tg.tree.query(w, distance_upper_bound=cut)
        ok = np.isfinite(d)
        r = np.einsum("ij,ij->i", tg.normals[j[ok]], w[ok] - tg.points[j[ok]])
        total += float(np.minimum((r / cut) ** 2, 1.0).sum()) + float((~ok).sum())
        n += len(o)
    return total / max(n, 1)


@dataclass
class OffsetSearch:
    """The result of :func:`search_offset` (seconds; the image shows the joint states of ``t + offset_s``)."""

    offset_s: float
    cost: float  # at the best offset
    inlier_ratio: float  # share of the points within 8 mm at the best offset
    cost_at_zero: float
    inlier_ratio_at_zero: float
    rise: float  # relative rise of the cost one frame either side of the best (the smaller side)
    fit: Fit  # the depth fit at the best offset
    curve: list = field(default_factory=list)  # [offset_s, cost, inlier_ratio] of every evaluation, by offset
    window_s: float = 0.0

    @property
    def observable(self) -> bool:
        """Whether the cost curve has a clear minimum (a moving arm in the frames)."""
        return self.rise >= MIN_RISE

    @property
    def at_window_edge(self) -> bool:
        return abs(self.offset_s) >= self.window_s - 1e-9

    @property
    def clearly_better(self) -> bool:
        """The best offset explains the depth clearly better than offset 0."""
        return (self.observable and abs(self.offset_s) > 0 and self.cost <= 0.85 * self.cost_at_zero
                and self.inlier_ratio >= self.inlier_ratio_at_zero + 0.02)

    def report(self) -> dict:
        return {"time_offset_s": self.offset_s, "time_offset_ms": 1e3 * self.offset_s,
                "time_offset_rise": self.rise, "time_offset_observable": self.observable,
                "time_offset_cost": self.cost, "time_offset_cost_at_zero": self.cost_at_zero,
                "inlier_ratio_at_best_offset": self.inlier_ratio, "inlier_ratio_at_zero_offset": self.inlier_ratio_at_zero,
                "time_offset_window_s": self.window_s,
                "time_offset_curve": [[1e3 * d, c, r] for d, c, r in self.curve]}


def search_offset(problem_at: Callable[[float], tuple[np.ndarray, list]], obs: Sequence[np.ndarray], X0: np.ndarray,
                  focal: float, scale: float, *, fps: float, window_s: float = 0.2, free_focal: bool = False,
                  free_scale: bool = False, tolerance_s: float = 0.001) -> OffsetSearch:
    """The constant offset (seconds) that explains a camera's depth best.

    ``problem_at(offset)``: ``(A, targets)`` of the camera's depth fit with the robot at the joint
    states of ``t + offset`` (:mod:`.register`); ``obs``: its observed points; ``X0``, ``focal``,
    ``scale``: the fit at offset 0, from which each trial offset's pose is refitted. Whole frames
    within ``+-window_s`` first, then a golden-section search within one frame of the best, to
    ``tolerance_s``."""
    evals: dict[float, tuple[float, float, Fit]] = {}

    def at(d: float, start: Fit | None = None) -> float:
        d = float(round(d, 9))
        if d not in evals:
            A, targets = problem_at(d)
            X, f, sc = (start.X, start.focal, start.scale) if start is not None else (X0, focal, scale)
            # from offset 0's pose a few centimetres may separate the poses; within a frame of the best, millimetres
            fit = fit_pose(obs, A, X, targets, f, scale0=sc, free_focal=free_focal, free_scale=free_scale,
                           schedule=(0.03, 0.02, 0.012, 0.008) if start is None else (0.012, 0.008), iterations=5)
            evals[d] = (fit_cost(obs, A, fit.X, targets, fit.focal, fit.scale), fit.inlier_ratio, fit)
        return evals[d][0]

    frame = 1.0 / fps
    k = max(1, int(math.floor(window_s * fps + 1e-9)))
    window = k * frame if window_s * fps < 1 else window_s
    for i in range(-k, k + 1):
        at(i * frame)
    best = min(evals, key=lambda d: evals[d][0])
    start = evals[best][2]
    lo, hi = max(best - frame, -window), min(best + frame, window)
    a, b = lo + (1 - _GOLDEN) * (hi - lo), lo + _GOLDEN * (hi - lo)
    fa, fb = at(a, start), at(b, start)
    while hi - lo > tolerance_s:
        if fa <= fb:
            hi, b, fb = b, a, fa
            a = lo + (1 - _GOLDEN) * (hi - lo)
            fa = at(a, start)
        else:
            lo, a, fa = a, b, fb
            b = lo + _GOLDEN * (hi - lo)
            fb = at(b, start)
    best = min(evals, key=lambda d: evals[d][0])
    cost, ratio, fit = evals[best]
    side = [evals[d][0] for d in evals if abs(abs(d - best) - frame) < 1e-6]
    if not side:
        side = [at(best + s * frame, fit) for s in (-1, 1) if abs(best + s * frame) <= window + 1e-9]
    rise = (min(side) - cost) / max(cost, 1e-6) if side else 0.0
    zero = evals[0.0]  # the coarse grid holds 0
    return OffsetSearch(offset_s=best, cost=cost, inlier_ratio=ratio, cost_at_zero=zero[0],
                        inlier_ratio_at_zero=zero[1], rise=float(rise), fit=fit,
                        curve=[[d, evals[d][0], evals[d][1]] for d in sorted(evals)], window_s=window)


def timing_refusal(camera: str, search: OffsetSearch, reason: str) -> str:
    """A refusal's message when an offset explains the depth clearly better than none: timing first."""
    ms = 1e3 * search.offset_s
    when = "behind (it lags)" if ms < 0 else "ahead"
    edge = (f" at the edge of the searched +-{1e3 * search.window_s:.0f} ms, so it may be larger"
            if search.at_window_edge else "")
    return (f"camera {camera!r}: the camera looks out of step with the joint states by about {abs(ms):.0f} ms{edge}: "
            f"its depth fits the robot {abs(ms):.0f} ms {when} of the joint states best ({100 * search.inlier_ratio:.0f}% "
            f"of the points within reach vs {100 * search.inlier_ratio_at_zero:.0f}% in step), yet no pose explains it "
            "even there. Check the recording's timestamps (a camera several frames late, or a drifting offset), "
            f"then the joint map and the depth's units. The fit's own verdict: {reason}")
