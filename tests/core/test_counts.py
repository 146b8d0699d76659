import numpy as np
import pytest

from dipnet.core.counts import is_real, whole_number


@pytest.mark.parametrize("value", [3, 3.0, np.int64(3), np.float32(3.0)])
def test_a_whole_number_of_any_numeric_type_is_an_int(value):
    assert whole_number("iterations", value) == 3
    assert type(whole_number("iterations", value)) is int


@pytest.mark.parametrize("value", [2.5, True, "3", None, float("nan"), float("inf")])
def test_anything_else_is_refused_naming_the_option(value):
    with pytest.raises(ValueError, match=r"budget must be a whole number, got"):
        whole_number("budget", value)


@pytest.mark.parametrize("value", ["abc", True, None, float("nan")])
def test_only_a_fraction_is_said_not_to_be_cut(value):
    """planner.planner.seed=abc ended with "(2.5 is not cut to 2)", which speaks of a fraction."""
    with pytest.raises(ValueError, match=r"seed must be a whole number, got \S+$"):
        whole_number("seed", value)
    with pytest.raises(ValueError, match=r"got 2.5 \(2.5 is not cut to 2\)$"):
        whole_number("seed", 2.5)


def test_a_lower_bound_is_named():
    assert whole_number("window", 1, low=1) == 1
    with pytest.raises(ValueError, match=r"window must be a whole number >= 1, got 0"):
        whole_number("window", 0, low=1)


def test_is_real_takes_numbers_and_refuses_booleans_text_and_complex():
    assert [is_real(v) for v in (3, 2.5, np.float32(1.0), float("nan"), -np.inf)] == [True] * 5
    assert [is_real(v) for v in (True, np.bool_(False), "3", 1j, None, [1])] == [False] * 6
