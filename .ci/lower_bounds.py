"""Print pip constraints that pin every dependency of pyproject.toml (core and extras) to its lower
bound, ``name==lower``: CI installs against them to test that the bounds hold. torch is left out
(it is installed first, at the README's pin) and so are dipnet's references to its own extras.

    python .ci/lower_bounds.py > lower.txt && pip install -c lower.txt -e ".[dev,report,sweeps]"
"""

from __future__ import annotations

import re
import sys
import tomllib
from pathlib import Path

SKIP = {"torch", "dipnet"}


def lower_bounds(pyproject: Path) -> dict[str, str]:
    """``{name: lower bound}`` of every requirement (core and optional); a requirement without a
    ``>=`` bound is an error: every dependency must have one."""
    project = tomllib.loads(pyproject.read_text())["project"]
    requirements = [*project["dependencies"], *(r for extra in project["optional-dependencies"].values() for r in extra)]
    out = {}
    for requirement in requirements:
        name = re.split(r"[<>=!~\[; ]", requirement, maxsplit=1)[0].lower()
        if name in SKIP:
            continue
        match = re.search(r">=\s*([\w.]+)", requirement)
        if not match:
            raise SystemExit(f"{requirement!r} has no lower bound (>=) in {pyproject}")
        out[name] = match.group(1)
    return out


if __name__ == "__main__":
    root = Path(__file__).resolve().parents[1]
    sys.stdout.write("".join(f"{name}=={version}\n" for name, version in sorted(lower_bounds(root / "pyproject.toml").items())))
