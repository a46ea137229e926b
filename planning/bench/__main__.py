"""``python -m planning.bench WHAT``: see :mod:`planning.bench.cli`."""

import sys

from .cli import main

sys.exit(main())
