"""The controller map phi: which joint configuration a motion image shows,
``q_{t+k} = phi(q_t, a_{t:t+k-1})`` (``docs/dataset-format.md``, "Motion images").

Absolute joint-position actions give the last commanded target, delta actions accumulate
(``absolute_indices`` stay absolute), and gripper actions map to the state's units through an
explicit affine map, optionally clipped. Frame ``t >= 1`` of an episode shows
``phi(q_{t-1}, a_{t-1})`` and frame 0 the measured state (:func:`frame_configurations`). Pure
functions over numpy arrays or torch tensors, any leading batch shape."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from imac_data.errors import InputError

__all__ = ["GripperActionMap", "Controller", "rollout", "frame_configurations", "joints_at", "SOURCES", "MODES"]

SOURCES = ("action", "state")
MODES = ("absolute", "delta")


@dataclass(frozen=True)
class GripperActionMap:
    """Action gripper value -> state gripper value at joint-vector ``index``:
    ``offset + scale * action``, then clipped to ``[low, high]`` where given."""

    index: int
    scale: float = 1.0
    offset: float = 0.0
    low: float | None = None
    high: float | None = None

    def __post_init__(self):
        for name in ("scale", "offset", "low", "high"):
            value = getattr(self, name)
            if value is not None and not math.isfinite(value):
                raise InputError(f"gripper action map of index {self.index}: {name} must be finite, got {value}")
        if self.low is not None and self.high is not None and self.low > self.high:
            raise InputError(f"gripper action map of index {self.index}: low {self.low} > high {self.high}")

    def to_dict(self) -> dict:
        return {"index": self.index, "scale": self.scale, "offset": self.offset, "low": self.low, "high": self.high}

    @classmethod
    def from_dict(cls, d, where: str = "gripper action map") -> GripperActionMap:
        if not isinstance(d, dict) or "index" not in d:
            raise InputError(f"{where}: expected a mapping with an 'index', got {d!r}")
        unknown = sorted(set(d) - {"index", "scale", "offset", "low", "high"})
        if unknown:
            raise InputError(f"{where}: unknown key(s) {unknown}")
        try:
            return cls(index=int(d["index"]), scale=float(d.get("scale", 1.0)), offset=float(d.get("offset", 0.0)),
                       low=None if d.get("low") is None else float(d["low"]),
                       high=None if d.get("high") is None else float(d["high"]))
        except (TypeError, ValueError) as e:
            raise InputError(f"{where}: {e}") from None


@dataclass(frozen=True)
class Controller:
    """How actions become joint configurations (the controller map phi).

    ``mode``: ``"absolute"`` (actions are joint-position targets) or ``"delta"``
    (actions add to the configuration). ``grippers``: the gripper mappings.
    ``absolute_indices``: in delta mode, indices whose action is an absolute
    target anyway (gripper indices are absolute by default: ``delta_grippers=False``).
    """

    mode: str = "absolute"
    grippers: tuple[GripperActionMap, ...] = ()
    absolute_indices: tuple[int, ...] = ()
    delta_grippers: bool = False
    clip_low: tuple[float, ...] | None = field(default=None)
    clip_high: tuple[float, ...] | None = field(default=None)

    def __post_init__(self):
        if self.mode not in MODES:
            raise InputError(f"controller mode must be one of {MODES}, got {self.mode!r}")
        object.__setattr__(self, "grippers", tuple(self.grippers))
        object.__setattr__(self, "absolute_indices", tuple(int(i) for i in self.absolute_indices))
        idx = [g.index for g in self.grippers]
        if len(set(idx)) != len(idx):
            raise InputError(f"controller: gripper index mapped twice in {idx}")

    def to_dict(self) -> dict:
        """JSON-able description (recorded in the dataset's ``meta/info.json``)."""
        return {"mode": self.mode, "grippers": [g.to_dict() for g in self.grippers],
                "absolute_indices": list(self.absolute_indices), "delta_grippers": self.delta_grippers,
                "clip_low": _json_floats(self.clip_low), "clip_high": _json_floats(self.clip_high)}

    @classmethod
    def from_dict(cls, d, where: str = "controller") -> Controller:
        """The inverse of :meth:`to_dict` (a recipe's ``robot.controller``, or ``info.json``);
        a ``None`` clip bound means no limit."""
        if not isinstance(d, dict):
            raise InputError(f"{where}: expected a mapping, got {d!r}")
        known = {"mode", "grippers", "absolute_indices", "delta_grippers", "clip_low", "clip_high"}
        unknown = sorted(set(d) - known)
        if unknown:
            raise InputError(f"{where}: unknown key(s) {unknown}; allowed: {sorted(known)}")

        def bounds(name, missing):
            v = d.get(name)
            if v is None:
                return None
            if not isinstance(v, (list, tuple)):
                raise InputError(f"{where}.{name}: expected a list of numbers (null = no limit), got {v!r}")
            try:
                return tuple(missing if x is None else float(x) for x in v)
            except (TypeError, ValueError):
                raise InputError(f"{where}.{name}: expected numbers or null, got {v!r}") from None

        grippers = d.get("grippers") or ()
        if not isinstance(grippers, (list, tuple)):
            raise InputError(f"{where}.grippers: expected a list, got {grippers!r}")
        try:
            absolute = tuple(int(i) for i in d.get("absolute_indices") or ())
        except (TypeError, ValueError):
            raise InputError(f"{where}.absolute_indices: expected integers, got {d.get('absolute_indices')!r}") from None
        return cls(mode=d.get("mode", "absolute"),
                   grippers=tuple(GripperActionMap.from_dict(g, f"{where}.grippers[{i}]")
                                  for i, g in enumerate(grippers)),
                   absolute_indices=absolute, delta_grippers=bool(d.get("delta_grippers", False)),
                   clip_low=bounds("clip_low", -math.inf), clip_high=bounds("clip_high", math.inf))

    def _absolute_mask(self, dof: int) -> np.ndarray:
        mask = np.zeros(dof, dtype=bool)
        if self.mode == "absolute":
            mask[:] = True
            return mask
        for i in self.absolute_indices:
            mask[i] = True
        if not self.delta_grippers:
            for g in self.grippers:
                mask[g.index] = True
        return mask

    def validate(self, dof: int) -> None:
        for i in [g.index for g in self.grippers] + list(self.absolute_indices):
            if not 0 <= i < dof:
                raise InputError(f"controller: index {i} out of range for a {dof}-D joint vector")
        for name in ("clip_low", "clip_high"):
            value = getattr(self, name)
            if value is not None and len(value) != dof:
                raise InputError(f"controller: {name} has {len(value)} entries, the joint vector {dof}")


# ----------------------------------------------------------------------------- array helpers


def _json_floats(values):
    """Floats for JSON: non-finite bounds (no limit) become None."""
    return None if values is None else [float(x) if math.isfinite(x) else None for x in values]


def _lib(x):
    return torch if isinstance(x, torch.Tensor) else np


def _as_array(x, what: str, like=None):
    if isinstance(x, torch.Tensor) or isinstance(like, torch.Tensor):
        t = torch.as_tensor(x)
        if like is not None:
            t = t.to(like)
        if not t.is_floating_point():
            t = t.to(torch.get_default_dtype())
        return t
    a = np.asarray(x)
    if not np.issubdtype(a.dtype, np.number):
        raise InputError(f"{what}: expected a numeric array, got dtype {a.dtype}")
    return a.astype(np.float64) if not np.issubdtype(a.dtype, np.floating) else a


def _check_finite(x, what: str) -> None:
    bad = ~torch.isfinite(x) if isinstance(x, torch.Tensor) else ~np.isfinite(x)
    if bad.any():
        where = tuple(int(i) for i in (torch.nonzero(bad)[0] if isinstance(x, torch.Tensor) else np.argwhere(bad)[0]))
        raise InputError(f"{what} has a non-finite value at position {where}")


def _map_grippers(x, controller: Controller):
    """Apply the gripper mappings (and clipping) to absolute targets ``x`` (..., D), out of place."""
    if not controller.grippers:
        return x
    out = x.clone() if isinstance(x, torch.Tensor) else x.copy()
    for g in controller.grippers:
        v = g.offset + g.scale * x[..., g.index]
        if g.low is not None or g.high is not None:
            v = v.clamp(g.low, g.high) if isinstance(v, torch.Tensor) else np.clip(v, g.low, g.high)
        out[..., g.index] = v
    return out


def _clip(q, controller: Controller):
    if controller.clip_low is None and controller.clip_high is None:
        return q
    lib = _lib(q)
    if controller.clip_low is not None:
        lo = _as_array(controller.clip_low, "clip_low", like=q)
        q = lib.maximum(q, lo)
    if controller.clip_high is not None:
        hi = _as_array(controller.clip_high, "clip_high", like=q)
        q = lib.minimum(q, hi)
    return q


# ----------------------------------------------------------------------------- phi


def rollout(q_t, actions, controller: Controller = Controller()):
    """``phi``: configurations ``q_{t+1..t+K}`` ``(*B, K, D)`` from the configuration at
    the reference frame ``q_t`` ``(*B, D)`` and the future actions ``a_{t..t+K-1}``
    ``(*B, K, D)``. Row ``k - 1`` of the result is ``phi(q_t, a_{t:t+k-1})``."""
    if isinstance(q_t, torch.Tensor) and not isinstance(actions, torch.Tensor):
        actions = torch.as_tensor(np.asarray(actions), device=q_t.device)
    actions = _as_array(actions, "actions")
    q_t = _as_array(q_t, "q_t", like=actions if isinstance(actions, torch.Tensor) else None)
    if actions.ndim < 2:
        raise InputError(f"actions must be (*B, K, D), got shape {tuple(actions.shape)}")
    D = actions.shape[-1]
    if q_t.shape[-1] != D or tuple(q_t.shape[:-1]) != tuple(actions.shape[:-2]):
        raise InputError(f"q_t shape {tuple(q_t.shape)} does not match actions shape {tuple(actions.shape)} "
                         f"(expected (*B, D) with (*B, K, D) actions)")
    controller.validate(D)
    _check_finite(q_t, "q_t")
    _check_finite(actions, "actions")
    absolute = _map_grippers(actions, controller)
    if controller.mode == "absolute":
        return _clip(absolute, controller)
    lib = _lib(actions)
    mask = controller._absolute_mask(D)
    cum = (actions.cumsum(-2) if lib is torch else np.cumsum(actions, axis=-2)) + q_t[..., None, :]
    m = torch.as_tensor(mask, device=actions.device) if lib is torch else mask
    q = lib.where(m, absolute, cum)
    return _clip(q, controller)


def frame_configurations(state, action=None, *, source: str = "action",
                         controller: Controller = Controller()):
    """The configuration each dataset frame's motion image shows, ``(T, D)``.

    ``source="state"``: the measured ``state``. ``source="action"``: frame 0 shows
    ``state[0]``, frame ``t >= 1`` shows ``phi(state[t-1], action[t-1])`` (one controller
    step from the measured state; for absolute actions: the command ``action[t-1]``).
    """
    if source not in SOURCES:
        raise InputError(f"motion source must be one of {SOURCES}, got {source!r}")
    state = _as_array(state, "state")
    if state.ndim != 2:
        raise InputError(f"state must be (T, D), got shape {tuple(state.shape)}")
    _check_finite(state, "state")
    if source == "state":
        return state
    if action is None:
        raise InputError("motion source 'action' needs the episode's actions")
    if isinstance(action, torch.Tensor) and not isinstance(state, torch.Tensor):
        state = torch.as_tensor(state).to(action)
    action = _as_array(action, "action", like=state if isinstance(state, torch.Tensor) else None)
    if tuple(action.shape) != tuple(state.shape):
        raise InputError(f"action shape {tuple(action.shape)} does not match state shape {tuple(state.shape)}")
    if len(state) == 0:
        return state
    step = rollout(state[:-1], action[:-1, None, :], controller)[:, 0]
    lib = _lib(state)
    return lib.concatenate([state[:1], step]) if lib is np else torch.cat([state[:1], step])


def joints_at(q: np.ndarray, frames) -> np.ndarray:
    """Joint vectors ``(N, D)`` of an episode's ``q`` ``(T, D)`` at fractional frame positions
    ``frames`` ``(N,)``: Catmull-Rom between frames (the cubic through the two frames either side, with
    the neighbours' central differences as slopes), clamped to ``[0, T - 1]``; whole frames give the
    recorded vector itself, bit for bit. A cubic, because a camera half a frame out of step sees the arm
    where a straight line between two samples is furthest off (docs/calibration.md)."""
    q = np.asarray(q, dtype=np.float64)
    T = len(q)
    f = np.clip(np.asarray(frames, dtype=np.float64), 0.0, T - 1.0)
    i1 = np.minimum(np.floor(f).astype(np.int64), T - 1)
    i2 = np.minimum(i1 + 1, T - 1)
    p0, p1, p2, p3 = q[np.maximum(i1 - 1, 0)], q[i1], q[i2], q[np.minimum(i2 + 1, T - 1)]
    t = (f - i1)[:, None]
    out = p1 + 0.5 * t * ((p2 - p0) + t * ((2.0 * p0 - 5.0 * p1 + 4.0 * p2 - p3) + t * (3.0 * (p1 - p2) + p3 - p0)))
    exact = t[:, 0] == 0.0
    out[exact] = p1[exact]
    return out
