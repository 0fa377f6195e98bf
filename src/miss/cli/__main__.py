"""``python -m miss.cli``: the ``miss`` command."""

import sys

from miss.cli import main

sys.exit(main())
