"""``python -m imac_data.validate ROOT [--full]``: check a built dataset (see
:mod:`imac_data.dataset.validate` for what is checked). Exit status 0 when valid, 2 with a
report when not; 3 when the machine fails it (:mod:`imac_data.cli`)."""

from __future__ import annotations

import argparse
from pathlib import Path

from imac_data.cli import EXIT_BAD_INPUT, EXIT_OK, quiet_libraries, run_command
from imac_data.dataset.validate import CHECKS, validate_dataset


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m imac_data.validate", description=__doc__.split("\n\n")[0])
    p.add_argument("root", type=Path, help="dataset directory")
    p.add_argument("--full", action="store_true", help="decode every frame of every video (default: samples)")
    p.add_argument("--sample", type=int, default=4, help="frames sampled per episode (default 4)")
    p.add_argument("--check", action="append", choices=[n for n, _ in CHECKS],
                   help="run only this check (repeatable)")
    args = p.parse_args(argv)
    quiet_libraries()

    def run() -> int:
        report = validate_dataset(args.root, full=args.full, sample=args.sample, checks=args.check)
        print(report.format())
        return EXIT_OK if report.ok else EXIT_BAD_INPUT

    return run_command(run)


if __name__ == "__main__":
    from imac_data.cli import exit_process

    exit_process(main())
