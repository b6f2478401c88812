"""``python -m formation``: the ``formation`` command."""

import sys

from formation.cli import main

sys.exit(main())
