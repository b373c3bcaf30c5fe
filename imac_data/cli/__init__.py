"""The command line: ``imac <command>`` or ``python -m imac_data <command>``.

One parser (:mod:`imac_data.cli.parser`), one module per command with its ``run(args)``,
and the exit codes and Ctrl-C handling of :mod:`imac_data.console`.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Sequence

from imac_data.cli.parser import COMMANDS, build_parser, command_of
from imac_data.console import exit_process, quiet_startup_interrupts

__all__ = ["main", "entry_point"]


def main(argv: Sequence[str] | None = None, *, prog: str = "imac") -> int:
    """Parse ``argv`` and run the command; returns its exit code."""
    quiet_startup_interrupts()  # Ctrl-C while the command's libraries load: one line, 130
    args = build_parser(prog).parse_args(list(sys.argv[1:] if argv is None else argv))
    command = importlib.import_module(COMMANDS[command_of(args)])
    return command.run(args)


def entry_point() -> None:
    """The ``imac`` console script."""
    exit_process(main())
