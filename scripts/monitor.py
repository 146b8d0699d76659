"""Watch a scan as it happens (or a finished one, or a replayed recording) in a browser.

    python scripts/monitor.py scans/demo                       # a scan running or finished in scans/demo
    python scripts/monitor.py --replay dipnet/data/real/3cats_fixture_3mm.csv --speed 20
    python scripts/monitor.py scans/demo --host 0.0.0.0        # reachable from the network: token printed

See docs/guide/monitor.md and :mod:`dipnet.monitor.cli`. Needs ``pip install -e ".[monitor,report]"``.
"""

import sys

from dipnet.monitor.cli import main

if __name__ == "__main__":
    sys.exit(main())
