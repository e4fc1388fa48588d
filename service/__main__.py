"""``python -m photomap``: the same as the ``photomap`` command."""

import sys

from photomap.cli.main import main

sys.exit(main())
