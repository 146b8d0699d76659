"""Generate the API reference: one page per subpackage of ``dipnet/`` (run by mkdocs-gen-files at build time).

Every module of a subpackage (its nested packages included, e.g. ``dipnet.rig.fake``) gets a
``::: module`` block that mkdocstrings renders from the docstrings, so a new module or subpackage appears
without editing anything here. Writes ``api/<subpackage>.md`` and ``api/SUMMARY.md`` (the literate-nav
of the section).
"""

from __future__ import annotations

from pathlib import Path

import mkdocs_gen_files

ROOT = Path(__file__).resolve().parents[2]
PACKAGE = ROOT / "dipnet"


def module_name(path: Path) -> str:
    """Dotted name of a module file or package ``__init__.py`` under the repository root."""
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def modules_of(package: Path) -> list[str]:
    """The package's own name, then every module below it (nested packages included), sorted by name."""
    files = sorted(p for p in package.rglob("*.py") if "__pycache__" not in p.parts and p.name != "__init__.py")
    packages = sorted(p for p in package.rglob("__init__.py") if p.parent != package)
    return [module_name(package / "__init__.py")] + sorted(module_name(p) for p in files + packages)


def top_level_page() -> str:
    """The ``dipnet`` page: the public API re-exported by ``dipnet/__init__.py`` and the top-level modules."""
    blocks = ["::: dipnet\n    options:\n      heading_level: 1\n      show_submodules: false\n      members: true\n"]
    for path in sorted(PACKAGE.glob("*.py")):
        if path.name != "__init__.py":
            blocks.append(f"::: {module_name(path)}\n")
    return "\n".join(blocks)


def subpackage_page(package: Path) -> str:
    """One subpackage: its docstring, then one block per module without repeating the submodules."""
    names = modules_of(package)
    blocks = [f"::: {names[0]}\n    options:\n      heading_level: 1\n      show_submodules: false\n      members: false\n"]
    blocks += [f"::: {name}\n    options:\n      show_submodules: false\n" for name in names[1:]]
    return "\n".join(blocks)


def main() -> None:
    nav = mkdocs_gen_files.Nav()
    with mkdocs_gen_files.open("api/index.md", "w") as f:
        f.write(top_level_page())
    nav["dipnet"] = "index.md"
    for package in sorted(p.parent for p in PACKAGE.glob("*/__init__.py")):
        page = f"{package.name}.md"
        with mkdocs_gen_files.open(f"api/{page}", "w") as f:
            f.write(subpackage_page(package))
        nav[f"dipnet.{package.name}"] = page
    with mkdocs_gen_files.open("api/SUMMARY.md", "w") as f:
        f.writelines(nav.build_literate_nav())


main()
