"""The one exception type user-facing code raises for bad input.

Messages name the file, key or field at fault, so a user can fix their data
without reading our source. CLIs print the message and exit non-zero.
"""


class InputError(ValueError):
    """Bad user input: a file, key, field or value that cannot be used as given."""
