"""The exception types user-facing code raises for faults it can explain.

Messages name the file, key or field at fault, so a user can fix their data
without reading our source. CLIs print the message and exit non-zero
(:func:`imac_data.console.run_command`: 2 for bad input, 3 for the environment).
"""


class InputError(ValueError):
    """Bad user input: a file, key, field or value that cannot be used as given."""


class EnvironmentFault(RuntimeError):
    """The machine, not the input: no space, a read-only file system, no permission,
    a path that cannot be created, another build holding the output's lock."""
