"""What the monitor tests share beside their fixtures: the small fake-rig scan's overrides. A plain module, so a test
file imports it by its own name (``from conftest import ...`` took whichever ``conftest`` was imported last: run with
``tests/experiments`` it was that folder's)."""

from __future__ import annotations

#: The small scan: 6 orientations, 4 mm steps (28 readings each) on the fake GRBL rig.
SCAN_OVERRIDES = ("n_dips=6", "protocol.step_mm=4", "progress=false", "fsync=false")
