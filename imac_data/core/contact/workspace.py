"""The workspace: the part of the world whose scene points enter the contact streams
(``docs/dataset-format.md``, "Far and invalid depth").

Far floors and walls, and saturated sensor depth, would make a chunk's percentile cap metres
long, so the scene cloud is cropped to a depth range (outside it: invalid depth, hole-filled
like 0) and a world box (outside it: no scene at all). By default the box is the robot's reach
(FK at joint vectors drawn within the URDF limits, plus a margin) and the range ends where the
depth codec saturates. Plain tensor functions, used offline and online alike."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from imac_data.errors import InputError

__all__ = ["Workspace", "WorkspaceSettings", "depth_in_range", "points_in_box", "reach_box", "resolve_workspace",
           "saturation_depth", "DEFAULT_MARGIN", "DEFAULT_REACH_SAMPLES"]

DEFAULT_MARGIN = 0.10  # metres added around the robot's reach
DEFAULT_REACH_SAMPLES = 1024  # joint vectors sampled for the reach box
_REACH_CACHE: dict = {}  # (URDF hash, robot config, samples, margin, seed) -> box: ~0.5 CPU s each


# ----------------------------------------------------------------------------- tensor functions


def depth_in_range(depth: torch.Tensor, near: float, far: float) -> torch.Tensor:
    """``(..., H, W)`` bool: valid depth inside the range, ``near <= d < far`` and ``d > 0``
    and finite (0, NaN, negative, saturated or beyond ``far`` = invalid)."""
    d = torch.as_tensor(depth)
    return torch.isfinite(d) & (d > 0) & (d >= near) & (d < far)


def points_in_box(points: torch.Tensor, lo, hi) -> torch.Tensor:
    """``(...,)`` bool: which points ``(..., 3)`` lie in the closed box ``[lo, hi]`` (world, metres)."""
    p = torch.as_tensor(points)
    lo_t = torch.as_tensor(lo, dtype=p.dtype, device=p.device)
    hi_t = torch.as_tensor(hi, dtype=p.dtype, device=p.device)
    return ((p >= lo_t) & (p <= hi_t)).all(dim=-1)


# ----------------------------------------------------------------------------- the resolved workspace


def _triple(value, where: str) -> tuple[float, float, float]:
    try:
        t = tuple(float(v) for v in value)
    except (TypeError, ValueError):
        raise InputError(f"{where}: expected [x, y, z] metres, got {value!r}") from None
    if len(t) != 3 or not all(math.isfinite(v) for v in t):
        raise InputError(f"{where}: expected three finite numbers [x, y, z] metres, got {value!r}")
    return t


def _depth_range(value, where: str) -> tuple[float, float]:
    try:
        near, far = (float(v) for v in value)
    except (TypeError, ValueError):
        raise InputError(f"{where}: expected [near, far] metres, got {value!r}") from None
    if not (math.isfinite(near) and near >= 0 and far > near):
        raise InputError(f"{where}: expected 0 <= near < far metres (far may be .inf), got {value!r}")
    return near, far


@dataclass(frozen=True)
class Workspace:
    """The crop of the contact streams' scene cloud: world box ``min``..``max`` and depth
    range ``[near, far)`` (metres), with ``source`` saying where they came from."""

    min: tuple[float, float, float]
    max: tuple[float, float, float]
    depth_range: tuple[float, float]
    source: str = "given"

    def __post_init__(self) -> None:
        lo, hi = _triple(self.min, "workspace.min"), _triple(self.max, "workspace.max")
        if not all(a < b for a, b in zip(lo, hi)):
            raise InputError(f"workspace: min must be below max on every axis, got min={lo}, max={hi}")
        object.__setattr__(self, "min", lo)
        object.__setattr__(self, "max", hi)
        object.__setattr__(self, "depth_range", _depth_range(self.depth_range, "workspace.depth_range"))

    @property
    def diagonal(self) -> float:
        """Length of the box's diagonal, metres: no two workspace points are farther apart."""
        return float(np.linalg.norm(np.subtract(self.max, self.min)))

    def valid_depth(self, depth: torch.Tensor) -> torch.Tensor:
        return depth_in_range(depth, *self.depth_range)

    def contains(self, points: torch.Tensor) -> torch.Tensor:
        return points_in_box(points, self.min, self.max)

    def to_dict(self) -> dict:
        """The ``info["imac"]["workspace"]`` form (JSON; an infinite ``far`` is written as null)."""
        near, far = self.depth_range
        return {"min": list(self.min), "max": list(self.max),
                "depth_range": [near, far if math.isfinite(far) else None], "source": self.source}

    @classmethod
    def from_dict(cls, d, where: str = "workspace") -> Workspace | None:
        """:meth:`to_dict`'s output back (None -> None: no crop)."""
        if d is None:
            return None
        if not isinstance(d, dict) or not {"min", "max", "depth_range"} <= set(d):
            raise InputError(f"{where}: expected {{min, max, depth_range, source}}, got {d!r}")
        try:
            near, far = d["depth_range"]
        except (TypeError, ValueError):
            raise InputError(f"{where}.depth_range: expected [near, far], got {d['depth_range']!r}") from None
        try:
            return cls(tuple(d["min"]), tuple(d["max"]), (near, math.inf if far is None else far),
                       str(d.get("source", "given")))
        except (InputError, TypeError) as e:
            raise InputError(f"{where}: {e}") from None


def as_workspace(value) -> Workspace | None:
    """A :class:`Workspace`, its dict form, or None (no crop)."""
    if value is None or isinstance(value, Workspace):
        return value
    if isinstance(value, dict):
        return Workspace.from_dict(value)
    raise InputError(f"workspace must be a Workspace, its dict form or None, got {type(value).__name__}")


# ----------------------------------------------------------------------------- recipe settings and defaults


@dataclass(frozen=True)
class WorkspaceSettings:
    """``augment.contact_workspace`` of a recipe; every field optional::

        contact_workspace:
          min: [-0.8, -0.6, -0.05]   # world box, metres (both or neither);
          max: [0.8, 0.6, 0.7]       #   neither = the robot's reach + margin
          margin: 0.1                # metres around the reach (only without min/max)
          depth_range: [0.1, 2.5]    # metres of z-depth; default [0, where the depth codec saturates)
    """

    min: tuple[float, ...] | None = None
    max: tuple[float, ...] | None = None
    margin: float | None = None
    depth_range: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        where = "augment.contact_workspace"
        if (self.min is None) != (self.max is None):
            raise InputError(f"{where}: give both min and max (a box), or neither (the robot's reach)")
        if self.min is not None:
            if self.margin is not None:
                raise InputError(f"{where}.margin: only applies to the default box (the robot's reach); "
                                 "with min and max the box is used as given")
            lo, hi = _triple(self.min, f"{where}.min"), _triple(self.max, f"{where}.max")
            if not all(a < b for a, b in zip(lo, hi)):
                raise InputError(f"{where}: min must be below max on every axis, got min={list(lo)}, max={list(hi)}")
        if self.margin is not None and not (math.isfinite(self.margin) and self.margin >= 0):
            raise InputError(f"{where}.margin: must be >= 0 metres, got {self.margin}")
        if self.depth_range is not None:
            _depth_range(self.depth_range, f"{where}.depth_range")


def _joint_ranges(robot) -> list[tuple[float, float]]:
    """URDF-unit sampling range of every dataset joint-vector entry's joint."""
    chain = robot._chain(torch.float64, torch.device("cpu"))
    low, high = chain.get_joint_limits()
    limits = dict(zip(chain.get_joint_parameter_names(), zip(low, high)))
    types = {j.name: j.joint_type for j in chain.get_joints()}
    out = []
    for i in range(robot.dof):
        name = robot.config.joint_entry(i).joint
        lo, hi = limits.get(name, (0.0, 0.0))
        if not (math.isfinite(lo) and math.isfinite(hi)):
            # continuous joints (and a revolute joint without <limit>) turn all the way round;
            # an unlimited slide has no reach to sample: held where it is
            lo, hi = (-math.pi, math.pi) if types.get(name) == "revolute" else (0.0, 0.0)
        out.append((float(lo), float(hi)))
    return out


def reach_box(robot, *, samples: int = DEFAULT_REACH_SAMPLES, margin: float = DEFAULT_MARGIN, seed: int = 0
              ) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """The robot's reach as a world box ``(min, max)``: every visual mesh's bounding-box
    corners at ``samples`` random joint vectors within the joint limits (plus the limits'
    midpoints), grown by ``margin`` and rounded outwards to the millimetre. Seeded, so the
    same robot always gives the same box (and a process computes it once)."""
    key = (robot.urdf_hash, robot.config, int(samples), float(margin), int(seed))
    if key not in _REACH_CACHE:
        _REACH_CACHE[key] = _reach_box(robot, int(samples), float(margin), int(seed))
    return _REACH_CACHE[key]


def _reach_box(robot, samples: int, margin: float, seed: int) -> tuple[tuple[float, ...], tuple[float, ...]]:
    if samples < 1:
        raise InputError(f"reach samples must be >= 1, got {samples}")
    if not robot.visual_meshes:
        raise InputError(f"robot {robot.name!r} has no visual meshes: its reach cannot be estimated; "
                         "give augment.contact_workspace min and max")
    ranges = np.array(_joint_ranges(robot))  # (D, 2) URDF units
    rng = np.random.default_rng(seed)
    u = ranges[:, 0] + rng.random((int(samples), robot.dof)) * (ranges[:, 1] - ranges[:, 0])
    u = np.concatenate([ranges.mean(axis=1)[None], u])
    entries = [robot.config.joint_entry(i) for i in range(robot.dof)]
    scale = np.array([e.scale for e in entries])
    offset = np.array([e.offset for e in entries])
    q = torch.as_tensor((u - offset) / scale, dtype=torch.float64)  # dataset units
    poses = robot.link_poses(q)
    lo = np.full(3, np.inf)
    hi = np.full(3, -np.inf)
    for mesh in robot.visual_meshes:
        v = np.asarray(mesh.vertices, dtype=np.float64)
        a, b = v.min(axis=0), v.max(axis=0)
        corners = torch.as_tensor(np.array([[x, y, z] for x in (a[0], b[0]) for y in (a[1], b[1])
                                            for z in (a[2], b[2])]))  # (8, 3) link frame
        T = poses[mesh.link]  # (N, 4, 4)
        world = corners @ T[:, :3, :3].transpose(-1, -2) + T[:, None, :3, 3]  # (N, 8, 3)
        lo = np.minimum(lo, world.reshape(-1, 3).min(dim=0).values.numpy())
        hi = np.maximum(hi, world.reshape(-1, 3).max(dim=0).values.numpy())
    lo = np.floor((lo - margin) * 1000.0) / 1000.0
    hi = np.ceil((hi + margin) * 1000.0) / 1000.0
    return tuple(float(x) for x in lo), tuple(float(x) for x in hi)


def saturation_depth(codec) -> float:
    """Where a :class:`~imac_data.core.depth.DepthCodec` saturates: its ``max_depth`` less half
    the 8-bit step there (rounded down to the millimetre). Depth beyond encodes to the codec's
    last codes, which decode to about ``max_depth`` whatever the true depth was."""
    far = codec.max_depth - float(codec.quantisation_step(codec.max_depth)) / 2
    return math.floor(far * 1000.0) / 1000.0


def resolve_workspace(settings: WorkspaceSettings | None, robot, far: float, *,
                      samples: int = DEFAULT_REACH_SAMPLES) -> Workspace:
    """The workspace a recipe's ``augment.contact_workspace`` describes, defaults filled in:
    the robot's reach (:func:`reach_box`) and the depth range ``[0, far)`` (the depth
    codec's :func:`saturation_depth`)."""
    s = settings if settings is not None else WorkspaceSettings()
    depth_range = tuple(s.depth_range) if s.depth_range is not None else (0.0, float(far))
    if s.min is not None:
        return Workspace(tuple(s.min), tuple(s.max), depth_range, source="recipe")
    margin = DEFAULT_MARGIN if s.margin is None else float(s.margin)
    lo, hi = reach_box(robot, samples=samples, margin=margin)
    source = f"robot reach: FK at {samples} joint vectors within the joint limits, + {margin:g} m"
    return Workspace(lo, hi, depth_range, source=source)
