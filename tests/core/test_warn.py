"""log_and_warn: one problem to the log and as a Python warning, pointing at the caller's caller."""

import logging
import warnings

import pytest

from dipnet.core.warn import log_and_warn

log = logging.getLogger("dipnet.test_warn")


def _library_function() -> None:
    log_and_warn(log, "100% of the dips disagree", RuntimeWarning, stacklevel=2)


def test_logs_and_warns_once_each(caplog):
    with caplog.at_level(logging.WARNING, logger="dipnet.test_warn"), warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        _library_function()
    assert [r.getMessage() for r in caplog.records] == ["100% of the dips disagree"]  # not %-formatted
    assert [(w.category, str(w.message)) for w in seen] == [(RuntimeWarning, "100% of the dips disagree")]
    assert seen[0].filename == __file__  # stacklevel 2: the line that called the library function
    assert seen[0].lineno == test_logs_and_warns_once_each.__code__.co_firstlineno + 3


def test_default_category_and_error_filter():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(UserWarning, match="disagree"):
            log_and_warn(log, "the dips disagree")
