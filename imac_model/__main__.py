"""``python -m imac_model <command>``: the ``imac-model`` command line."""

from imac_model.cli import entry_point

if __name__ == "__main__":
    entry_point()
