"""``python -m imac_model.evaluate``: see :mod:`imac_model.evaluate.cli`."""

import sys

from imac_model.evaluate.cli import main

if __name__ == "__main__":
    sys.exit(main())
