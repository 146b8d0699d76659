"""checked_flag: true or false (or 1 and 0), nothing that Python merely reads as true."""

import numpy as np
import pytest

from dipnet.core.flags import checked_flag


@pytest.mark.parametrize("value", ["no", "false", "maybe", 2, 0.5, None])
def test_anything_but_true_or_false_is_refused_by_name(value):
    with pytest.raises(ValueError, match=r"^coarse_to_fine must be true or false, got "):
        checked_flag("coarse_to_fine", value)


def test_true_false_and_their_integers_are_flags():
    assert [checked_flag("x", v) for v in (True, False, 1, 0, np.bool_(True))] == [True, False, True, False, True]
