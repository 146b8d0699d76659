"""Memory estimates: byte formatting, totals and the description's order."""

import pytest

from dipnet.core.memory import MemoryEstimate, ResourceError, available_memory, format_bytes


@pytest.mark.parametrize("n,text", [(0, "0 B"), (999, "999 B"), (1500, "1.5 KB"), (2.4e16, "24 PB"),
                                    (746e6, "746 MB"), (3e9, "3 GB")])
def test_bytes_are_written_in_powers_of_1000(n, text):
    assert format_bytes(n) == text


def test_the_estimate_adds_its_parts_and_names_the_largest_first():
    estimate = MemoryEstimate({"grid": 1e6, "solver": 3e9, "operator": 2e8, "unused": 0.0})
    assert estimate.total == pytest.approx(3.201e9)
    assert estimate.describe() == "~3.2 GB (solver 3 GB, operator 200 MB, grid 1 MB)"


def test_available_memory_is_positive_when_known_and_resource_errors_are_value_errors():
    free = available_memory()
    assert free is None or free > 0
    assert issubclass(ResourceError, ValueError)
