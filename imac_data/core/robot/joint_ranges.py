"""Recorded joint ranges against the URDF's limits: the check that catches a wrong unit.

A joint vector recorded in degrees (many LeRobot datasets), in -100..100 or in encoder
ticks, mapped to a URDF in radians and metres without the matching ``scale``, renders
a robot that is plainly wrong, and nothing else fails. Before a build starts, each entry's
recorded range [min, max] is mapped through its joint-map entry and compared with the
URDF ``<limit>`` of its joint. URDF limits are often a little conservative and encoders
overshoot, so only a range outside the limits by more than :data:`SLACK` of the limit
span (at least :data:`MIN_SLACK`) is reported; continuous joints and joints without
limits are not checked. The result is a list of messages: the build and ``qa calibrate``
print them as a warning (a URDF's limits may simply be wrong) and go on.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["SLACK", "MIN_SLACK", "BUILD_GOES_ON", "joint_range_problems", "joint_range_warning"]

SLACK = 0.1  # of the limit span
MIN_SLACK = {"revolute": 0.05, "prismatic": 0.002}  # radians, metres
_UNITS = {"revolute": "rad", "prismatic": "m"}


def joint_range_problems(robot, lo, hi) -> list[str]:
    """Entries of the dataset joint vector whose recorded range ``lo[i]..hi[i]`` (the
    dataset's units; ``(D,)`` arrays) maps outside the URDF limits of the joint it drives
    (``robot``: a :class:`~imac_data.core.robot.model.RobotModel`). One message per entry, naming the
    index, the joint, both ranges and, where it fits, the likely unit."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    problems = []
    for i in range(robot.dof):
        entry = robot.config.joint_entry(i)
        if entry.joint not in robot.joint_limits or not (math.isfinite(lo[i]) and math.isfinite(hi[i])):
            continue
        kind, lower, upper = robot.joint_limits[entry.joint]
        a, b = sorted((entry.offset + entry.scale * lo[i], entry.offset + entry.scale * hi[i]))
        slack = max(SLACK * (upper - lower), MIN_SLACK[kind])
        if a >= lower - slack and b <= upper + slack:
            continue
        unit = _UNITS[kind]
        msg = (f"joint vector index {i} ({entry.joint!r}): recorded {lo[i]:.5g}..{hi[i]:.5g}"
               + ("" if entry.is_identity else f", mapped to {a:.5g}..{b:.5g} {unit}")
               + f", outside the URDF limits {lower:.5g}..{upper:.5g} {unit}")
        degrees = [entry.offset + entry.scale * math.radians(v) for v in (lo[i], hi[i])]
        beyond_a_turn = max(abs(a), abs(b)) > 2 * math.pi  # radians of a limited joint never get there
        if kind == "revolute" and beyond_a_turn and lower - slack <= min(degrees) and max(degrees) <= upper + slack:
            msg += f"; if it records degrees, give it scale: {entry.scale * math.pi / 180:.7g}"
        problems.append(msg)
    return problems


BUILD_GOES_ON = "The build goes on and renders the joints as recorded."


def joint_range_warning(robot, lo, hi, *, source, recipe, then: str = BUILD_GOES_ON) -> str | None:
    """The build's warning for :func:`joint_range_problems` (``None`` when there is none):
    what is out of range, in ``source``, and where to fix it (``recipe``); ``then``: what the
    command does next (``qa calibrate`` runs the same check and says its own)."""
    problems = joint_range_problems(robot, lo, hi)
    if not problems:
        return None
    # a simulator's soft limits overshoot too (MuJoCo's ALOHA fingers by 4 mm): the joint is drawn where it was
    # recorded, so the warning says what would make the drawing wrong rather than that it is
    return (f"warning: {source}: recorded joint values lie outside the URDF limits of robot {robot.name!r}:\n  - "
            + "\n  - ".join(problems)
            + f"\n  If robot.joint_map in {recipe} maps a unit wrongly (each entry maps the recorded unit to radians "
            f"or metres: q_urdf = offset + scale * value), the rendered robot will not match the images. {then}")
