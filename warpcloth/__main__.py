"""``python -m warpcloth``: the ``warpcloth`` command line (warpcloth/cli.py) where the script is not on PATH."""

import sys

from warpcloth.cli import main

if __name__ == "__main__":
    sys.exit(main())
