"""Hardware only: motion controllers (GRBL, Marlin), sensors, the scan runner, adaptive scans, the fake rig.

Ports are opened with ``serial.serial_for_url``; :func:`register_url_handlers` adds the fake
rig's ``fakerig://<world>/<device>`` scheme (module :mod:`dipnet.rig.protocol_fakerig`).
"""

from __future__ import annotations

import serial


def register_url_handlers() -> None:
    """Let ``serial.serial_for_url`` open ``fakerig://`` URLs (idempotent)."""
    if "dipnet.rig" not in serial.protocol_handler_packages:
        serial.protocol_handler_packages.append("dipnet.rig")
