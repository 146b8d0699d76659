"""calibration=self: the config group builds a SelfCalibrator that hands a source's recording to self_calibrate."""

import pytest
import torch
from hydra import compose, initialize_config_module
from hydra.utils import instantiate

from dipnet.calibration import self_calibration
from dipnet.calibration.self_calibration import SelfCalibrator, partial_volume
from dipnet.core.geometry import RigGeometry
from dipnet.core.grid import Grid
from dipnet.core.reconstruction import Reconstruction
from dipnet.preprocessing.sources import Recording


def test_the_config_group_builds_the_calibrator_with_its_options():
    with initialize_config_module(config_module="dipnet.conf", version_base="1.3"):
        cfg = compose(config_name="config", overrides=["calibration=self", "calibration.iterations=2",
                                                       "calibration.params=[pivot_mm,tilt_zero_deg]"])
    calibrator = instantiate(cfg.calibration)
    assert isinstance(calibrator, SelfCalibrator)
    assert calibrator.params == ("pivot_mm", "tilt_zero_deg") and calibrator.iterations == 2
    assert calibrator.shape == "binary" and calibrator.tank is None and calibrator.gain_solver is None


def test_run_hands_the_recording_and_options_to_self_calibrate(monkeypatch):
    seen = {}
    monkeypatch.setattr(self_calibration, "self_calibrate", lambda raw, grid, solver, params, **kw: seen.update(
        raw=raw, grid=grid, solver=solver, params=params, **kw) or "result")
    finish, initial, grid = (lambda m: m), RigGeometry(pivot_mm=3.0), Grid(8, 3, 40.0)
    recording = Recording("raw scan", initial, smooth=True, finish=finish)
    calibrator = SelfCalibrator(params=["pivot_mm"], iterations=3, dip_offset_sigma_mm=1, max_section_change=0.1)
    assert calibrator.run(recording, grid, "solver", 8, "factory") == "result"
    assert seen["raw"] == "raw scan" and seen["params"] == ("pivot_mm",) and seen["initial"] is initial
    assert seen["smooth"] is True and seen["finish"] is finish and seen["operator_factory"] == "factory"
    assert (seen["iterations"], seen["dip_offset_sigma_mm"], seen["max_section_change"], seen["n_slabs"]) == (3, 1.0, 0.1, 8)


def test_the_partial_volume_share():
    grid = Grid(4, 3, 4.0)
    occupancy = torch.zeros(grid.shape, dtype=torch.float64)
    occupancy[0, 0, :2] = 1.0
    occupancy[1, 1, :2] = 0.5  # two voxels of half occupancy: 1 of the 3 units of volume
    assert partial_volume(Reconstruction(occupancy, grid)) == 1.0 / 3.0


def test_the_section_bias_grows_with_the_partial_volume_and_is_capped():
    """``self_section_bias``: none for a fully resolved shape, 0.95 p^2 below the cap (bunny-like p = 0.1:
    about 1 %; hammer-like p = 0.3: about 8.5 %), never more than 11 %."""
    from dipnet.calibration.model import self_section_bias

    assert self_section_bias(0.0) == 0.0
    assert self_section_bias(0.1) == pytest.approx(0.0095)
    assert self_section_bias(0.3) == pytest.approx(0.0855)
    assert self_section_bias(0.6) == self_section_bias(1.0) == 0.11


def test_the_calibrated_section_is_the_gain_corrected_for_the_field_deficit():
    """The section the joint step hands on is ``assumed / gain / (1 - self_section_bias(partial))``."""
    import warnings

    from dipnet.calibration.model import self_section_bias
    from dipnet.calibration.self_calibration import self_calibrate
    from dipnet.core.orientations import fibonacci_hemisphere
    from dipnet.shapes import Ball
    from dipnet.simulator.physics import Tank, simulate_scan
    from dipnet.solvers.voxel import VoxelSolver

    raw = simulate_scan(Ball(25.0), fibonacci_hemisphere(24), tank=Tank(60000.0),
                        geometry=RigGeometry(cross_section_mm2=0.92 * 60000.0), progress=False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        result = self_calibrate(raw, Grid(16, extent=80.0), VoxelSolver(iterations=40, progress=False),
                                ("cross_section_mm2",))
    step = result.history[-1]
    assert step["section_bias"] == self_section_bias(step["partial_volume"]) > 0
    assert step["cross_section_mm2"] == pytest.approx(60000.0 / step["gain"] / (1 - step["section_bias"]), rel=1e-12)
