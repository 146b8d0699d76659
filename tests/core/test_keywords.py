"""Keyword discovery for the config checks: own parameters, and ``**options`` followed through ``forwards_to``."""

from dipnet.core.keywords import accepted_keywords, forwards_to


def inner(a, *, b=1):
    return a, b


def deepest(c=0, **anything):
    return c


@forwards_to(inner)
def outer(x, y=2, **options):
    return inner(x, **options)


@forwards_to(deepest)
def open_ended(z=0, **options):
    return deepest(**options)


class Wrapper:
    @forwards_to(outer)
    def __init__(self, w=0, **options):
        self.options = options


def test_a_closed_signature_is_its_own_keywords():
    assert accepted_keywords(inner) == {"a", "b"}


def test_options_are_followed_through_the_declared_targets():
    assert accepted_keywords(outer) == {"x", "y", "a", "b"}
    assert accepted_keywords(Wrapper) == {"w", "x", "y", "a", "b"}


def test_undeclared_or_open_ended_options_accept_anything():
    assert accepted_keywords(deepest) is None
    assert accepted_keywords(open_ended) is None
    assert outer.forwards_to == (inner,)
