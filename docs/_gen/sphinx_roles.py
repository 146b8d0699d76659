"""A griffe extension for the API reference: the docstrings' Sphinx markup shown as Markdown.

The docstrings cross-reference with Sphinx roles (``:func:`name```, ``:class:`~pkg.mod.Name```) and end a
paragraph before a literal block with ``::``. mkdocstrings renders Markdown, so the roles would show as
raw text: each becomes inline code of the name as Sphinx would print it (``~`` keeps the last component,
``title <target>`` the title), and a paragraph's ``::`` a single colon (the indented block below it is a code
block in Markdown too).
"""

from __future__ import annotations

import re
from typing import Any

import griffe

ROLE = re.compile(r":(?:py:)?(?:class|func|mod|meth|attr|data|exc|obj|const):`(?P<target>[^`]+)`")
LITERAL_MARKER = re.compile(r"(?<=\S)::$", re.M)


def role_text(target: str) -> str:
    """What Sphinx shows for a role's target: ``~a.b.C`` -> ``C``; ``title <a.b>`` -> ``title``."""
    title = re.match(r"(?P<title>.+?)\s*<[^>]+>$", target)
    if title:
        return title["title"]
    return target[1:].rsplit(".", 1)[-1] if target.startswith("~") else target


def to_markdown(text: str) -> str:
    """A docstring with its Sphinx roles as inline code and its ``::`` markers as colons."""
    text = ROLE.sub(lambda m: f"`{role_text(m['target'])}`", text)
    return LITERAL_MARKER.sub(":", text)


class SphinxRoles(griffe.Extension):
    """Rewrite every docstring once it is loaded."""

    def on_instance(self, *, obj: griffe.Object, **kwargs: Any) -> None:
        if obj.docstring is not None:
            obj.docstring.value = to_markdown(obj.docstring.value)
