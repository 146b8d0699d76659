"""Generate the reference of every config group and option from ``conf/`` (run by mkdocs-gen-files).

Walks ``conf/*.yaml`` (the primary configs: ``config.yaml`` for ``scripts/reconstruct.py``, ``scan.yaml`` for
``scripts/scan.py``) and ``conf/<group>/*.yaml`` (nested groups such as ``hydra/callbacks`` included), and
writes ``reference/config.md``: per group its choices and the default choice, per choice its header comment
and a table of every option with its default value as written in the YAML and the comment next to it.
The parse is checked against ``yaml.safe_load`` of the same file: a key the line parser missed or invented
fails the build, so the page cannot drift from the files.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

ROOT = Path(__file__).resolve().parents[2]
CONF = ROOT / "conf"
KEY = re.compile(r"^(?P<indent>\s*)(?P<key>[A-Za-z_][\w@/.+-]*)\s*:(?:\s+(?P<rest>.*)|\s*)$")


@dataclass
class Option:
    """One key of a YAML file: its keys from the top, default as written, and its comment (continuation lines
    joined)."""

    keys: tuple[str, ...]
    value: str
    comment: str
    indent: int

    @property
    def path(self) -> str:
        """The dotted path a command-line override uses (``solver.priors.tv.weight``)."""
        return ".".join(self.keys)


@dataclass
class ConfigFile:
    """A parsed YAML config: header comment, the ``defaults`` list, options in file order, free-standing notes."""

    header: str
    defaults: list[tuple[str, str]] = field(default_factory=list)
    options: list[Option] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)


def split_comment(text: str) -> tuple[str, str]:
    """Split ``value  # comment`` at the first ``#`` outside quotes that starts the text or follows a space."""
    quote = None
    for i, ch in enumerate(text):
        if quote:
            quote = None if ch == quote else quote
        elif ch in "'\"":
            quote = ch
        elif ch == "#" and (i == 0 or text[i - 1].isspace()):
            return text[:i].strip(), text[i + 1:].strip()
    return text.strip(), ""


def parse(text: str) -> ConfigFile:
    """Parse a Hydra YAML file line by line, keeping the comments that ``yaml`` drops."""
    lines = text.splitlines()
    header: list[str] = []
    i = 0
    while i < len(lines) and lines[i].lstrip().startswith("#"):
        if not lines[i].startswith("# @package"):
            header.append(lines[i].lstrip("#").strip())
        i += 1
    out = ConfigFile(header="\n".join(header).strip())
    stack: list[tuple[int, str]] = []  # (indent, key) of the open mappings
    last: Option | None = None
    in_defaults = False
    for line in lines[i:]:
        stripped = line.strip()
        if not stripped:
            continue
        indent = len(line) - len(line.lstrip())
        if stripped.startswith("#"):
            comment = stripped.lstrip("#").strip()
            if last is not None and indent > last.indent:
                last.comment = f"{last.comment} {comment}".strip()  # continuation of the comment above
            else:
                out.notes.append(comment)
            continue
        if stripped.startswith("- "):
            item, comment = split_comment(stripped[2:])
            if in_defaults:
                out.defaults.append((item, comment))
            elif last is not None:
                last.value = f"{last.value}\n- {item}".strip()
                last.comment = f"{last.comment} {comment}".strip()
            continue
        match = KEY.match(line)
        if match is None:
            raise ValueError(f"cannot parse config line: {line!r}")
        value, comment = split_comment(match["rest"] or "")
        while stack and stack[-1][0] >= indent:
            stack.pop()
        in_defaults = indent == 0 and match["key"] == "defaults"
        if in_defaults:
            last = None
            continue
        last = Option(tuple(k for _, k in stack) + (match["key"],), value, comment, indent)
        out.options.append(last)
        if not value:
            stack.append((indent, match["key"]))
    return out


def check_against_yaml(parsed: ConfigFile, text: str, name: str) -> None:
    """Raise if a key of ``parsed`` is not in the YAML, or a YAML leaf has no parsed key at or above it."""
    data = yaml.safe_load(text) or {}
    data.pop("defaults", None)

    def leaves(node: Any, prefix: tuple[str, ...]) -> list[tuple[str, ...]]:
        if isinstance(node, dict) and node:
            return [leaf for k, v in node.items() for leaf in leaves(v, prefix + (str(k),))]
        return [prefix]

    known = set()  # keys that hold a value (a mapping written inline counts), not just a block of keys
    for opt in parsed.options:
        node: Any = data
        for part in opt.keys:
            if not isinstance(node, dict) or part not in node:
                raise ValueError(f"{name}: parsed key {opt.path} is not in the YAML")
            node = node[part]
        if opt.value or not (isinstance(node, dict) and node):
            known.add(opt.keys)
    for leaf in leaves(data, ()) if data else []:
        if not any(leaf[:n] in known for n in range(1, len(leaf) + 1)):
            raise ValueError(f"{name}: YAML key {'.'.join(leaf)} was not parsed")


def load(path: Path) -> ConfigFile:
    """Parse and check one config file."""
    text = path.read_text()
    parsed = parse(text)
    check_against_yaml(parsed, text, str(path.relative_to(ROOT)))
    return parsed


def cell(text: str) -> str:
    """Text safe inside a Markdown table cell."""
    return text.replace("|", "\\|").replace("\n", "<br>")


def code_cell(text: str) -> str:
    """A default value as inline code in a table cell (multi-line block lists shown one item per line)."""
    if not text:
        return ""
    return "<br>".join(f"`{cell(part)}`" for part in text.split("\n"))


def render_file(parsed: ConfigFile, title: str, level: int) -> str:
    """Markdown for one file: heading, header comment, defaults, option table, notes."""
    out = [f"{'#' * level} {title}\n"]
    if parsed.header:
        out.append("```text\n" + parsed.header + "\n```\n")
    if parsed.defaults:
        out.append("Defaults list:\n")
        out += [f"- `{item}`" + (f": {comment}" if comment else "") for item, comment in parsed.defaults]
        out.append("")
    rows = [o for o in parsed.options if o.value or o.comment]
    if rows:
        out.append("| option | default | comment |\n|---|---|---|")
        out += [f"| `{o.path}` | {code_cell(o.value)} | {cell(o.comment)} |" for o in rows]
        out.append("")
    out += [f"*Note:* {cell(n)}\n" for n in parsed.notes]
    return "\n".join(out)


def group_defaults(config: ConfigFile) -> dict[str, str]:
    """The default choice of each group named in a primary config's defaults list (``group: choice``)."""
    found = {}
    for item, _ in config.defaults:
        if ":" in item and not item.startswith(("override", "optional", "_self_")):
            group, choice = (s.strip() for s in item.split(":", 1))
            found[group] = choice
    return found


def page() -> str:
    """The whole configuration reference."""
    primaries = {p.stem: load(p) for p in sorted(CONF.glob("*.yaml"))}
    defaults = {g: c for cfg in primaries.values() for g, c in group_defaults(cfg).items()}
    groups: dict[str, list[Path]] = {}
    for path in sorted(CONF.rglob("*.yaml")):
        if path.parent != CONF:
            groups.setdefault(path.parent.relative_to(CONF).as_posix(), []).append(path)
    out = [
        "# Configuration reference\n",
        "Generated from `conf/` when the site is built (`docs/_gen/config_reference.py`): every primary config,",
        "every group, its choices, and every option with its default as written in the YAML and the comment",
        "next to it. Set an option on the command line (`resolution=64`, `solver.priors.tv.weight=3e-3`), pick",
        "a group's choice (`solver=voxel`), add a key that is not in the config with `+` (`+planner=adaptive`",
        "for `scan.py`). The configs ship inside the package as `dipnet.conf`.\n",
        "## Primary configs\n",
    ]
    scripts = {"config": "scripts/reconstruct.py", "scan": "scripts/scan.py"}
    for name, parsed in primaries.items():
        used = f" (`{scripts[name]}`)" if name in scripts else ""
        out.append(render_file(parsed, f"`{name}.yaml`{used}", 3))
    out.append("## Groups\n")
    out.append("| group | choices | default |\n|---|---|---|")
    for group, files in groups.items():
        out.append(f"| [`{group}`](#group-{group.replace('/', '-')}) | "
                   + ", ".join(f"`{p.stem}`" for p in files) + f" | `{defaults.get(group, 'none')}` |")
    out.append("")
    for group, files in groups.items():
        out.append(f"### `{group}` {{ #group-{group.replace('/', '-')} }}\n")
        out.append(f"Choose with `{group}=<choice>`; default: `{defaults.get(group, 'none')}`.\n")
        for path in files:
            out.append(render_file(load(path), f"`{group}={path.stem}`", 4))
    return "\n".join(out)


if __name__ in ("__main__", "<run_path>"):
    import mkdocs_gen_files

    with mkdocs_gen_files.open("reference/config.md", "w") as f:
        f.write(page())
    mkdocs_gen_files.set_edit_path("reference/config.md", "../conf")
