"""``python -m warptan.cli``: the ``warptan`` command."""

import sys

from warptan.cli import main

sys.exit(main())
