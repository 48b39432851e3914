"""``python -m vpr_explorer.cli``: the ``vpr-explorer`` console script."""

import sys

from vpr_explorer.cli import main

sys.exit(main())
