"""The docs generators: the config reference reads conf/ faithfully, the gallery reads every example."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml
from script_modules import load_module

ROOT = Path(__file__).resolve().parents[2]


def _load(name: str):
    return load_module(ROOT / "docs" / "_gen" / f"{name}.py", f"docs_gen_{name}")


config_reference = _load("config_reference")
gallery = _load("gallery")


def test_an_option_keeps_its_default_and_its_comment():
    parsed = config_reference.parse("a: 1   # one\nb:\n  c: 'x # y'  # the c\n  d: [p, q]\n"
                                    "        # more about d\ne: {k: 2}\n")
    got = {o.path: (o.value, o.comment) for o in parsed.options}
    assert got == {"a": ("1", "one"), "b": ("", ""), "b.c": ("'x # y'", "the c"),
                   "b.d": ("[p, q]", "more about d"), "e": ("{k: 2}", "")}


def test_a_key_the_parser_misses_fails_the_check():
    text = "a:\n  b: 1\n"
    parsed = config_reference.parse(text)
    parsed.options.pop()  # as if the line parser had skipped b
    with pytest.raises(ValueError, match="a.b was not parsed"):
        config_reference.check_against_yaml(parsed, text, "t.yaml")


def test_every_config_file_is_in_the_reference_with_every_option():
    page = config_reference.page()
    for path in sorted((ROOT / "conf").rglob("*.yaml")):
        group = path.parent.relative_to(ROOT / "conf").as_posix()
        assert (f"`{path.name}`" if group == "." else f"`{group}={path.stem}`") in page, path
    # every top-level option of the main config, with its value as yaml reads it
    for key, value in yaml.safe_load((ROOT / "conf" / "config.yaml").read_text()).items():
        if key != "defaults" and not isinstance(value, dict):
            assert f"| `{key}` | `{'null' if value is None else str(value).lower()}` |" in page, key


def test_every_example_has_a_gallery_page():
    for path in sorted((ROOT / "examples").glob("*.py")):
        title, text = gallery.example_page(path)
        assert title and f"examples/{path.name}" in text and "import" in text


def test_an_example_without_a_docstring_is_refused():
    with pytest.raises(ValueError, match="docstring"):
        gallery.split_script("import dipnet\n")
