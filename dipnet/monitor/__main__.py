"""``python -m dipnet.monitor RUN_DIR``: the monitor (see :mod:`dipnet.monitor.cli`)."""

import sys

from dipnet.monitor.cli import main

sys.exit(main())
