"""The true shape of a recording, when the recording names it (fake-rig scans).

A raw scan made by ``scripts/scan.py`` on the fake rig carries its full scan config in the
header, including the simulated object (``config.scan.rig.fake.shape``, a Hydra ``_target_``
spec). Reconstructing such a scan with ``source=recorded`` can then be scored like a
simulated job: the job (the only code that instantiates a config) builds the shape from the
spec found here. Real recordings name no shape and get no shape metrics.
"""

from __future__ import annotations

from pathlib import Path

from dipnet.core.rawscan import read_rawscan


def shape_spec(header_config: dict) -> dict | None:
    """The ``_target_`` spec of the fake rig's object in a raw-scan header ``config``, or ``None``."""
    fake = ((header_config or {}).get("scan") or {}).get("rig", {}).get("fake") or {}
    spec = fake.get("shape")
    return spec if isinstance(spec, dict) and "_target_" in spec else None


def recorded_shape_spec(path: str | Path) -> dict | None:
    """The shape spec a raw scan (``.jsonl``) names in its header, or ``None`` (other files, real rigs)."""
    path = Path(path)
    return shape_spec(read_rawscan(path).header.config) if path.suffix.lower() == ".jsonl" else None
