"""The true shape of a recording, when the recording knows it (fake-rig scans).

A raw scan made by ``scripts/scan.py`` on the fake rig carries its full scan config in the
header, including the simulated object (``config.scan.rig.fake.shape``, a Hydra ``_target_``
spec). Reconstructing such a scan with ``source=recorded`` can then be scored like a
simulated job. Real recordings name no shape and get no shape metrics.
"""

from __future__ import annotations

import logging
from pathlib import Path

from hydra.utils import instantiate

from dipnet.core.rawscan import read_rawscan
from dipnet.shapes import Shape

log = logging.getLogger(__name__)


def shape_spec(header_config: dict) -> dict | None:
    """The ``_target_`` spec of the fake rig's object in a raw-scan header ``config``, or ``None``."""
    fake = ((header_config or {}).get("scan") or {}).get("rig", {}).get("fake") or {}
    spec = fake.get("shape")
    return spec if isinstance(spec, dict) and "_target_" in spec else None


def shape_from_recording(path: str | Path) -> Shape | None:
    """The shape a raw scan (``.jsonl``) names in its header, or ``None`` (other files, real rigs)."""
    path = Path(path)
    if path.suffix != ".jsonl":
        return None
    spec = shape_spec(read_rawscan(path).header.config)
    if spec is None:
        return None
    shape = instantiate(spec)
    log.info("%s names its shape (%s, radius %.1f mm): scoring against it", path, shape.name, shape.radius())
    return shape
