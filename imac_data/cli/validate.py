"""``imac validate ROOT [--full] [--restore-imac-from ORIGINAL]``: check a built dataset (after putting
back an ``imac`` block a LeRobot tool dropped); exit 0 when valid, 2 with a report."""

from __future__ import annotations

import argparse

from imac_data.console import EXIT_BAD_INPUT, EXIT_OK, quiet_libraries, run_command
from imac_data.dataset.merge import restore_imac_block
from imac_data.dataset.validate import validate_dataset


def run(args: argparse.Namespace) -> int:
    quiet_libraries()

    def body() -> int:
        if args.restore_imac_from is not None:
            restore_imac_block(args.root, args.restore_imac_from)
            print(f"restored the imac block of {args.root} from {args.restore_imac_from}")
        report = validate_dataset(args.root, full=args.full, sample=args.sample, checks=args.check)
        print(report.format())
        return EXIT_OK if report.ok else EXIT_BAD_INPUT

    return run_command(body)
