"""How a camera is refined: :class:`RefineConfig`, validated at the boundary and loadable
back from what was saved (``RefineConfig(**saved)``)."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

from imac_data.errors import InputError

__all__ = ["METHODS", "RefineConfig"]

METHODS = ("gradient", "nelder-mead", "powell")



@dataclass(frozen=True)
class RefineConfig:
    """How :func:`refine_camera` optimises (validated on construction; every field is a
    plain number, string or tuple, so ``RefineConfig(**saved)`` restores a saved one)."""

    method: str = "gradient"  # one of METHODS
    levels: tuple[float, ...] = (0.25, 0.5, 1.0)  # image scales, coarse to fine
    min_level_width: int = 48  # skip coarser levels than this (pixels)
    refine_focal: bool = False  # also scale fx, fy together
    iou_weight: float = 0.0  # measured: the IoU term slows convergence and costs time (benchmark --ablation)
    edge_weight: float = 0.1
    robust: str = "cauchy"  # edge loss: "cauchy" (log: far boundaries stop pulling) or "huber" (linear)
    edge_scale_px: float = 1.0  # the edge loss's scale (level px): residuals beyond it count less
    max_iterations: int = 12  # renders per level (gradient) / evaluations per level / 10 (derivative-free)
    step_px: float = 4.0  # trust region: the largest image motion of one gradient step (coarsest level px)
    fine_step_px: float = 2.0  # the same on the finer levels, which start close to their optimum
    tolerance_px: float = 0.02  # a level ends when a step moves the image less than this
    pad: float = 0.15  # rendered margin around the image, as a fraction of its larger side
    lbfgs_iterations: int = 6

    def __post_init__(self) -> None:
        def bad(name, why):
            raise InputError(f"RefineConfig.{name}: {why} (got {getattr(self, name)!r})")

        if self.method not in METHODS:
            bad("method", f"must be one of {METHODS}")
        if self.robust not in ("huber", "cauchy"):
            bad("robust", "must be 'huber' or 'cauchy'")
        levels = tuple(float(s) for s in self.levels) if isinstance(self.levels, (list, tuple)) else None
        if not levels or any(not (0 < s <= 1) for s in levels) or list(levels) != sorted(levels):
            bad("levels", "must be increasing image scales in (0, 1]")
        object.__setattr__(self, "levels", levels)
        for name in ("iou_weight", "edge_weight"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) >= 0):
                bad(name, "must be a finite number >= 0")
        if self.iou_weight == 0 and self.edge_weight == 0:
            bad("edge_weight", "iou_weight and edge_weight cannot both be 0")
        for name in ("edge_scale_px", "step_px", "fine_step_px", "tolerance_px"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) > 0):
                bad(name, "must be a finite number > 0")
        if not (0 <= self.pad <= 1):
            bad("pad", "must be in [0, 1]")
        for name in ("min_level_width", "max_iterations", "lbfgs_iterations"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                bad(name, "must be an integer >= 1")

    def to_dict(self) -> dict:
        return {f.name: (list(getattr(self, f.name)) if f.name == "levels" else getattr(self, f.name))
                for f in fields(self)}
