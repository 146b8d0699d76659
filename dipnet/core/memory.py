"""Memory figures shared by every size check: the estimate by part, bytes in words, what is available now."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

UNITS = ("B", "KB", "MB", "GB", "TB", "PB", "EB")
#: Readings per dip a scan or a simulation may take (100 m of travel at 1 mm steps: no rig dips that deep).
MAX_READINGS_PER_DIP = 100_000


class ResourceError(ValueError):
    """The run needs more memory than the machine has (the message gives both figures)."""


@dataclass
class MemoryEstimate:
    """Estimated peak memory of a run, by part (bytes)."""

    parts: dict[str, float] = field(default_factory=dict)

    @property
    def total(self) -> float:
        return float(sum(self.parts.values()))

    def describe(self) -> str:
        """``"~1.2 GB (operator 600 MB, solver 400 MB, ...)"``, largest parts first."""
        parts = sorted(self.parts.items(), key=lambda kv: -kv[1])
        return f"~{format_bytes(self.total)} ({', '.join(f'{k} {format_bytes(v)}' for k, v in parts if v > 0)})"


def format_bytes(n: float) -> str:
    """``24e15`` -> ``"24 PB"`` (powers of 1000, 2 significant digits)."""
    n = float(n)
    unit = 0
    while n >= 1000 and unit < len(UNITS) - 1:
        n /= 1000
        unit += 1
    return f"{n:.2g} {UNITS[unit]}" if n < 100 else f"{n:.0f} {UNITS[unit]}"


def available_memory() -> int | None:
    """Bytes of memory available to a new allocation now, or ``None`` when unknown."""
    try:
        import psutil  # optional: only if already installed
    except ImportError:
        psutil = None
    if psutil is not None:
        return int(psutil.virtual_memory().available)
    meminfo = Path("/proc/meminfo")
    if meminfo.is_file():
        for line in meminfo.read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return None

