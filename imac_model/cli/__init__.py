"""The ``imac-model`` command line (``python -m imac_model <command>``): train, sample, evaluate,
experiment, ranking, plan. One parser (:mod:`imac_model.cli.parser`), one module per command."""

from __future__ import annotations

import importlib
import sys
from collections.abc import Sequence

from imac_data.console import exit_process, quiet_startup_interrupts
from imac_model.cli.parser import COMMANDS, build_parser, command_of

__all__ = ["main", "entry_point"]


def main(argv: Sequence[str] | None = None, *, prog: str = "imac-model") -> int:
    """Parse ``argv`` and run the command; returns its exit code."""
    quiet_startup_interrupts()
    args = build_parser(prog).parse_args(list(sys.argv[1:] if argv is None else argv))
    return importlib.import_module(COMMANDS[command_of(args)]).run(args)


def entry_point() -> None:
    """The ``imac-model`` console script."""
    exit_process(main())
