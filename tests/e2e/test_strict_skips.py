"""Under ``DIPNET_STRICT_SKIPS=1`` (what ``.ci/run`` sets) a skip fails unless the test is
marked ``hardware`` or ``browser``: a clone that misses data or a dependency cannot pass CI."""

from __future__ import annotations

from pathlib import Path

import pytest

pytest_plugins = ["pytester"]

CONFTEST = (Path(__file__).parents[1] / "conftest.py").read_text()

TESTS = """
import pytest

def test_passes():
    assert True

@pytest.mark.hardware
def test_rig():
    pytest.skip("no rig")

@pytest.mark.browser
def test_browser():
    pytest.skip("no chromium")

def test_missing_data():
    pytest.skip("data not found")
"""


def _run(pytester: pytest.Pytester, monkeypatch: pytest.MonkeyPatch, strict: str):
    monkeypatch.setenv("DIPNET_STRICT_SKIPS", strict)
    pytester.makeconftest(CONFTEST)
    pytester.makeini("[pytest]\nmarkers =\n    hardware: rig\n    browser: chromium\n")
    pytester.makepyfile(test_skips=TESTS, test_module_skip="import pytest\npytest.importorskip('no_such_module_x')\n")
    return pytester.runpytest("-p", "no:cacheprovider", "--continue-on-collection-errors")


def test_unexpected_skips_fail_under_strict_mode(pytester, monkeypatch):
    result = _run(pytester, monkeypatch, "1")
    result.assert_outcomes(passed=1, skipped=2, failed=1, errors=1)
    result.stdout.fnmatch_lines(["*test_missing_data skipped (Skipped: data not found)*"])


def test_skips_are_plain_skips_without_strict_mode(pytester, monkeypatch):
    result = _run(pytester, monkeypatch, "0")
    result.assert_outcomes(passed=1, skipped=4)
