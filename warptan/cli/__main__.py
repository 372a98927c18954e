"""``python -m warptan.cli``: the ``warptan`` command."""

import sys

from warptan.cli import main

if __name__ == "__main__":
    sys.exit(main())
