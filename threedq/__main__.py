"""``python -m threedq`` = the ``threedq`` command."""

import sys

from threedq.cli import main

sys.exit(main())
