"""Generate the example gallery from ``examples/*.py`` (run by mkdocs-gen-files at build time).

Each script's module docstring becomes its page's text (its first line the title) and the rest of the
script is shown below it, so a page always shows the code that ``tests/e2e/test_examples.py`` runs.
Writes ``examples/<name>.md``, ``examples/index.md`` and ``examples/SUMMARY.md``.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "examples"
ORDER = ["quickstart", "own_mesh", "three_cats", "fake_rig_scan", "reference_ball", "adaptive_planning",
         "sweep_and_compare"]   # reading order of the gallery


def split_script(source: str) -> tuple[str, str]:
    """``(docstring, code after it)`` of a script; raises if it has no module docstring."""
    tree = ast.parse(source)
    doc = ast.get_docstring(tree)
    if not doc:
        raise ValueError("an example needs a module docstring: it is the gallery page's text")
    end = tree.body[0].end_lineno
    return doc, "\n".join(source.splitlines()[end:]).strip() + "\n"


def example_page(path: Path) -> tuple[str, str]:
    """``(title, Markdown)`` of one example: the docstring's first line is ``Title: summary``."""
    doc, code = split_script(path.read_text())
    first, _, body = doc.partition("\n")
    title, _, summary = first.rstrip(".").partition(": ")
    lead = f"{summary[:1].upper()}{summary[1:]}.\n\n" if summary else ""
    text = (f"# {title}\n\n{lead}{body.strip()}\n\n"
            f"Run it from the repository root: `python examples/{path.name} [OUTPUT_DIR]`.\n\n"
            f"```python title=\"examples/{path.name}\"\n{code}```\n")
    return title, text


def ordered(paths: list[Path]) -> list[Path]:
    """The examples in reading order: those of ``ORDER`` first, any other after them by name."""
    rank = {name: i for i, name in enumerate(ORDER)}
    return sorted(paths, key=lambda p: (rank.get(p.stem, len(ORDER)), p.stem))


if __name__ in ("__main__", "<run_path>"):
    import mkdocs_gen_files

    nav = mkdocs_gen_files.Nav()
    rows = []
    nav["Gallery"] = "index.md"
    for path in ordered(list(EXAMPLES.glob("*.py"))):
        title, text = example_page(path)
        with mkdocs_gen_files.open(f"examples/{path.stem}.md", "w") as f:
            f.write(text)
        mkdocs_gen_files.set_edit_path(f"examples/{path.stem}.md", f"../examples/{path.name}")
        nav[title] = f"{path.stem}.md"
        summary = split_script(path.read_text())[0].partition("\n")[0].rstrip(".").partition(": ")[2]
        rows.append(f"| [{title}]({path.stem}.md) | {summary} | `examples/{path.name}` |")
    with mkdocs_gen_files.open("examples/index.md", "w") as f:
        f.write("# Example gallery\n\nSmall scripts that each run in well under a minute on 2 cores "
                "(small grids and few dips: the numbers they print are not the benchmarks'). "
                "`tests/e2e/test_examples.py` runs every one of them "
                "(`python -m pytest -m slow tests/e2e/test_examples.py`).\n\n"
                "| example | what it does | script |\n|---|---|---|\n" + "\n".join(rows) + "\n")
    with mkdocs_gen_files.open("examples/SUMMARY.md", "w") as f:
        f.writelines(nav.build_literate_nav())
