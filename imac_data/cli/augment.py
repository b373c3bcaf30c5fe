"""``imac augment``: add the streams to an existing LeRobot dataset."""

from __future__ import annotations

import argparse

from imac_data.build.augment import augment_existing
from imac_data.console import quiet_libraries, run_command, silence_progress_bars
from imac_data.lerobot_compat import default_root
from imac_data.recipes import find_recipe, load_recipe


def run(args: argparse.Namespace) -> int:
    quiet_libraries()
    if args.no_progress:
        silence_progress_bars()

    def body() -> None:
        recipe = load_recipe(args.recipe if args.recipe.suffix else find_recipe(str(args.recipe)))
        root = args.root or default_root(args.repo)
        augment_existing(root, recipe, args.source, progress=not args.no_progress, device=args.device)
        print(f"augmented {args.repo} at {root}")

    return run_command(body)
