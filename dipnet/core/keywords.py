"""Which keyword options a function or class takes, following ``**options`` it passes on (for the config checks)."""

from __future__ import annotations

import inspect
from collections.abc import Callable
from typing import TypeVar

F = TypeVar("F", bound=Callable)


def forwards_to(*targets: Callable) -> Callable[[F], F]:
    """Declare that the decorated function (or ``__init__``) passes its ``**options`` on to
    ``targets``, so that :func:`accepted_keywords` knows which options it takes."""
    def mark(fn: F) -> F:
        fn.forwards_to = targets  # type: ignore[attr-defined]
        return fn
    return mark


def accepted_keywords(target: Callable) -> set[str] | None:
    """The keyword arguments ``target`` (a function or class) takes, following ``**options``
    through :func:`forwards_to`; ``None`` when it takes ``**options`` it does not declare."""
    params = inspect.signature(target).parameters.values()
    names = {p.name for p in params if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)}
    if not any(p.kind == p.VAR_KEYWORD for p in params):
        return names
    forwards = getattr(target.__init__ if inspect.isclass(target) else target, "forwards_to", None)
    if forwards is None:
        return None
    for inner in forwards:
        more = accepted_keywords(inner)
        if more is None:
            return None
        names |= more
    return names
