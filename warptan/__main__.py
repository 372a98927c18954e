"""``python -m warptan`` runs the ``warptan`` command line."""

import sys

from warptan.cli import main

if __name__ == "__main__":
    sys.exit(main())
