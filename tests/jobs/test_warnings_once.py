"""Each warning of a command-line job shown once, through logging (dipnet.jobs.warnings_once)."""

from __future__ import annotations

import logging
import warnings

import pytest

from dipnet.jobs import warnings_once


def test_a_warning_that_was_logged_is_shown_once(monkeypatch, capfd):
    monkeypatch.setattr(warnings_once, "_installed", False)
    monkeypatch.setattr(warnings_once, "_logged", set())
    monkeypatch.setattr(warnings, "showwarning", warnings.showwarning)
    factory = logging.getLogRecordFactory()
    log = logging.getLogger("dipnet.test_warnings_once")
    handler = logging.StreamHandler()                                 # stderr, as Hydra's console handler
    for name in ("dipnet.test_warnings_once", warnings_once.WARNINGS_LOGGER):
        logging.getLogger(name).addHandler(handler)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("always")
            warnings_once.log_warnings_once()
            log.warning("the reconstruction holds too much")
            warnings.warn("the reconstruction holds too much", UserWarning)   # the same finding: not again
            warnings.warn("only warned, never logged", UserWarning)           # shown once, through logging
            with pytest.raises(UserWarning):                                  # filters still come first
                warnings.simplefilter("error")
                warnings.warn("an error now", UserWarning)
    finally:
        logging.setLogRecordFactory(factory)
        for name in ("dipnet.test_warnings_once", warnings_once.WARNINGS_LOGGER):
            logging.getLogger(name).removeHandler(handler)
    err = capfd.readouterr().err
    assert err.count("the reconstruction holds too much") == 1
    assert err.count("only warned, never logged") == 1 and "UserWarning: only warned" in err
