"""``python -m imac_data.build --repo local/<name>``: the main job, as ``imac build``."""

import sys

from imac_data.cli import main
from imac_data.console import exit_process

if __name__ == "__main__":
    exit_process(main(["build", *sys.argv[1:]], prog="python -m imac_data.build"))
