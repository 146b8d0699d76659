"""calibration=self: the config group builds a SelfCalibrator that hands a source's recording to self_calibrate."""

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
