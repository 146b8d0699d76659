"""The README's Python API example runs as written."""

import re
from pathlib import Path

README = Path(__file__).resolve().parents[2] / "README.md"


def test_python_api_example_runs(tmp_path, monkeypatch):
    text = README.read_text()
    section = text.split("## Python API", 1)[1]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    exec(compile(code, "README.md", "exec"), namespace)
    recon, grid, check = namespace["recon"], namespace["grid"], namespace["check"]
    assert recon.binary.shape == grid.shape and recon.binary.any()
    assert (tmp_path / "dips.npz").is_file()
    assert check.verdict == "consistent" and abs(check.volume_ratio - 1) < 0.05, check.warnings


def test_the_api_checks_name_data_in_another_unit_and_a_result_that_does_not_explain_its_dips(tmp_path):
    """Before, from Python: a measurement 1000 x too large (litres read as mL) was solved without a word, into the same
    shape (minnorm's Otsu level is scale-free), holding a thousandth of the measured volume. The README now calls the
    two checks ``scripts/reconstruct.py`` runs, which the package exports."""
    import warnings
    from dataclasses import replace

    import pytest

    import dipnet

    grid = dipnet.Grid(20, ndim=3, extent=100.0)
    dirs = dipnet.fibonacci_hemisphere(40)
    op = dipnet.make_operator(grid, dirs)
    shape = dipnet.builtin_shape("ball", 3, radius=0.6 * grid.radius)
    _, meas = dipnet.simulate_measurement(shape, dirs, grid=grid, progress=False)
    scaled = replace(meas, profiles=meas.profiles * 1000)
    with pytest.raises(dipnet.MeasurementValidationError, match="more than the working ball's .*wrong units"):
        dipnet.validate_measurement(scaled, grid)
    recon = dipnet.make_solver("minnorm", progress=False).solve(scaled, op)
    with pytest.warns(dipnet.DataConsistencyWarning):
        check = dipnet.check_consistency(scaled, op, recon)
    assert check.verdict == "inconsistent" and check.volume_ratio < 2e-3
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert dipnet.check_consistency(meas, op,
                                        dipnet.make_solver("minnorm", progress=False).solve(meas, op)).verdict \
            == "consistent"
