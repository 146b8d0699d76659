"""The package's floors: each room (subpackage) of ``dipnet/`` imports only rooms above it in
:data:`FLOORS` (docs/development.md, "Code map"), lazy imports inside functions included."""

import ast
from pathlib import Path

import dipnet

FLOORS = ("core", "operators", "shapes", "preprocessing", "simulator", "solvers", "calibration", "evaluation",
          "planning", "outputs", "experiments", "rig", "jobs")
PACKAGE = Path(dipnet.__file__).parent


def _dipnet_imports(path: Path):
    """``(line, room)`` of every ``dipnet.<room>`` import in the module at ``path``."""
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom) and node.level == 0 and (node.module or "").startswith("dipnet."):
            yield node.lineno, node.module.split(".")[1]
        elif isinstance(node, ast.Import):
            yield from ((node.lineno, a.name.split(".")[1]) for a in node.names if a.name.startswith("dipnet."))


def test_every_room_has_a_floor():
    rooms = {p.name for p in PACKAGE.iterdir() if (p / "__init__.py").exists()}
    assert rooms == set(FLOORS), f"rooms without a floor: {rooms - set(FLOORS)}; floors without a room: " \
                                 f"{set(FLOORS) - rooms}"


def test_no_room_imports_a_room_below_it():
    rank = {room: i for i, room in enumerate(FLOORS)}
    climbs = [f"{path.relative_to(PACKAGE.parent)}:{line} {path.relative_to(PACKAGE).parts[0]} -> {other}"
              for room in FLOORS for path in sorted((PACKAGE / room).rglob("*.py"))
              for line, other in _dipnet_imports(path) if rank.get(other, -1) > rank[room]]
    assert not climbs, "imports of a room below:\n" + "\n".join(climbs)


def test_the_core_imports_no_other_room():
    others = [(path.name, line, room) for path in (PACKAGE / "core").rglob("*.py")
              for line, room in _dipnet_imports(path) if room != "core"]
    assert not others
