"""``python -m imac_data <command>``: the ``imac`` command line."""

from imac_data.cli import entry_point

if __name__ == "__main__":
    entry_point()
