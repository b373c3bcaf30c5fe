"""``imac robot joints URDF``: a URDF's joints, limits, mimics and visual links, and a recipe
``robot:`` block to start from; with ``--lerobot-robot``, its joint map in LeRobot's units."""

from __future__ import annotations

import argparse

from imac_data.console import run_command
from imac_data.core.robot.lerobot_units import LEROBOT_ARMS, joint_map, read_calibration
from imac_data.core.robot.urdf_summary import format_summary, guess_gripper_links, recipe_block, summarize_urdf


def run(args: argparse.Namespace) -> int:
    def body() -> int:
        summary = summarize_urdf(args.urdf, dict(args.package_dir))
        mapped, units = None, None
        if args.lerobot_robot:  # checked before anything is printed
            units = args.lerobot_units or LEROBOT_ARMS[args.lerobot_robot].units
            calibration = read_calibration(args.lerobot_calibration) if args.lerobot_calibration else None
            limits = {j.name: (j.lower, j.upper) for j in summary.drivable}
            mapped = joint_map(args.lerobot_robot, limits, units=units, calibration=calibration)
        print(format_summary(summary))
        print()
        print(recipe_block(summary, guess_gripper_links(summary), joint_map=mapped, units=units), end="")
        return 0

    return run_command(body)
