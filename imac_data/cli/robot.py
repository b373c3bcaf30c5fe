"""``imac robot joints URDF``: a URDF's joints, limits, mimics and visual links, and a recipe
``robot:`` block to start from."""

from __future__ import annotations

import argparse

from imac_data.console import run_command
from imac_data.core.robot.urdf_summary import format_summary, guess_gripper_links, recipe_block, summarize_urdf


def run(args: argparse.Namespace) -> int:
    def body() -> int:
        summary = summarize_urdf(args.urdf, dict(args.package_dir))
        print(format_summary(summary))
        print()
        print(recipe_block(summary, guess_gripper_links(summary)), end="")
        return 0

    return run_command(body)
