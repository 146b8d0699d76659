"""Recordings to measurements: the authors' CSV, fixture, rig geometry, symmetry, interpolation, calibration."""

from __future__ import annotations

import dataclasses
import math
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from dipnet.core.grid import Grid
from dipnet.core.orientations import fibonacci_hemisphere, rig_to_direction
from dipnet.simulator.physics import DipProtocol, LevelSensor, Tank, simulate_scan
from dipnet.preprocessing.preprocess import preprocess
from dipnet.core.rawscan import RawScanFileError
from dipnet.core.geometry import RigGeometry
from dipnet.preprocessing.recorded import (calibrate_cross_section, expand_symmetry, interpolate_orientations,
                                           geometry_start_heights, prepare_recording, read_authors_csv,
                                           read_raw_recording, read_scan, subtract_fixture, symmetry_group,
                                           truncated_orientations)
from dipnet.shapes import Ball, Box
from dipnet.simulator.simulate import simulate_measurement

from dipnet.preprocessing.datasets import CATS_CSV as CSV


@pytest.fixture(scope="module")
def cats_csv() -> Path:
    return CSV


class Union:
    """Disjoint shapes as one (volumes add)."""

    ndim = 3

    def __init__(self, *parts):
        self.parts = parts
        self.volume = sum(p.volume for p in parts)
        self.name = "union"

    def volume_below(self, directions, heights):
        return sum(p.volume_below(directions, heights) for p in self.parts)

    def radius(self):
        return max(p.radius() for p in self.parts)


def three_balls(radius: float = 12.0, ring: float = 22.0, z: float = 5.0) -> Union:
    """Three balls at azimuths 0, 120, 240 degrees: symmetric under D3 with a mirror plane at 0."""
    return Union(*(Ball(radius, (ring * math.cos(a), ring * math.sin(a), z))
                   for a in np.radians([0.0, 120.0, 240.0])))


# --------------------------------------------------------------------------- authors' CSV
def test_authors_csv_reader(cats_csv):
    raw = read_authors_csv(cats_csv)
    assert len(raw.orientations) == 32 and all(o.complete and o.n_readings == 111 for o in raw.orientations)
    assert sorted({o.tilt_deg for o in raw.orientations}) == [0, 5, 10, 15, 20, 25, 30, 35]
    assert sorted({o.spin_deg for o in raw.orientations}) == [0, 20, 40, 60]
    assert [(o.tilt_deg, o.spin_deg) for o in raw.orientations[:5]] == [(0, 0), (0, 20), (0, 40), (0, 60), (5, 0)]
    o = raw.orientations[0]
    assert o.stage_mm[0] == 25.0 and o.stage_mm[-1] == 355.0 and np.all(np.diff(o.stage_mm) == 3.0)
    h = raw.header
    assert (h.quantity, h.step_mm, h.tank_cross_section_mm2, h.resolution) == ("level_mm", 3.0, 183600.0, 0.04)
    assert 188.0 < o.values.min() and o.values.max() < 200.0
    cut = truncated_orientations(raw)
    tilt = {o.k: o.tilt_deg for o in raw.orientations}
    assert all(tilt[k] >= 15 for k in cut) and all(o.k in cut for o in raw.orientations if o.tilt_deg >= 25)


def test_authors_csv_levels_off_the_authors_quantum_leave_it_unknown(cats_csv, tmp_path):
    """Levels converted to inches under WaterLevel_mm were read as the authors' 0.04 mm readings: the consistency
    check then named that quantum (coarse against the tiny slabs) as the cause and left out the unit hint."""
    rows = cats_csv.read_text().splitlines()
    inches = tmp_path / "inches.csv"
    inches.write_text("\n".join([rows[0]] + [",".join(r.split(",")[:4] + [f"{float(r.split(',')[4]) / 25.4:.5f}"])
                                               for r in rows[1:]]) + "\n")
    assert read_authors_csv(inches).header.resolution is None
    m = read_raw_recording(inches, Grid(16, extent=360.0), truncated="keep")
    assert m.metadata["reading_quantum"] is None
    assert read_raw_recording(cats_csv, Grid(16, extent=360.0), truncated="keep").metadata["reading_quantum"] == 0.04


def test_authors_csv_errors(tmp_path):
    bad = tmp_path / "bad.csv"
    bad.write_text("SN,R1,R2,H,L\n1,0,0,-25,188\n")
    with pytest.raises(RawScanFileError, match="bad.csv:1: expected the header"):
        read_authors_csv(bad)
    bad.write_text("SN,R1_deg,R2_deg,Height_mm,WaterLevel_mm\n1,0,0,-25,abc\n")
    with pytest.raises(RawScanFileError, match="bad.csv:2"):
        read_authors_csv(bad)
    with pytest.raises(RawScanFileError, match="not found"):
        read_authors_csv(tmp_path / "missing.csv")
    head = "SN,R1_deg,R2_deg,Height_mm,WaterLevel_mm\n"
    bad.write_text(head + "1,0,0,-25,188\n2,0,0,-28,188.5\n3,0,0\n")  # the audit's case: a cut-off last row
    with pytest.warns(UserWarning, match=r"bad.csv:4: the last row is cut off \(3 of 5 fields\): dropped"):
        assert read_authors_csv(bad).orientations[0].n_readings == 2
    bad.write_text(head + "1,0,0,-25,188\n2,0,0\n3,0,0,-31,189\n")  # not the last: an error
    with pytest.raises(RawScanFileError, match="bad.csv:3: expected 5 fields, got 3"):
        read_authors_csv(bad)
    bad.write_text(head + "1,0,0,-25,188\n2,0,0,-28,188.5\n3,0,0,-25,188\n4,0,0,-28,188.5\n")  # one angle twice
    with pytest.raises(RawScanFileError, match="bad.csv:4: .* the same R1, R2 dipped twice in a row"):
        read_authors_csv(bad)


def test_an_authors_csv_cut_off_mid_dip_leaves_its_last_dip_out(tmp_path):
    """A CSV cut on a row boundary has no cut-off row: its last dip (17th of the cats, 25 of 111 rows) was read as
    complete, its total 6% of the others', and the result came out with a residual of 0.96. Now it is incomplete,
    left out (warned, ``dips_incomplete_dropped``) as a raw scan's dip without its ``complete`` line."""
    lines = CSV.read_text().splitlines()
    cut = tmp_path / "cut.csv"
    cut.write_text("\n".join(lines[:1801]) + "\n")
    with pytest.warns(UserWarning, match=r"cut.csv:1801: the last dip ends at Height_mm -94, short of the -355 "):
        scan = read_authors_csv(cut)
    assert [o.complete for o in scan.orientations] == [True] * 16 + [False]
    whole = tmp_path / "whole.csv"
    whole.write_text("\n".join(lines[:1777]) + "\n")  # 16 whole dips: nothing cut off
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert all(o.complete for o in read_authors_csv(whole).orientations)


def test_cats_preprocessing(cats_csv):
    grid = Grid(24, extent=360.0)
    m = read_raw_recording(cats_csv, grid, truncated="keep", smooth=True)
    info = m.metadata["recorded"]
    assert m.profiles.shape == (32, 24) and m.slab_thickness == pytest.approx(15.0)
    assert torch.allclose(m.directions, rig_to_direction([o // 4 * 5 for o in range(32)],
                                                         [o % 4 * 20 for o in range(32)]))
    assert (m.profiles >= 0).all()  # monotone cumulative volume, also after smoothing
    cumulative = torch.cumsum(m.profiles, 1)
    assert (torch.diff(cumulative, dim=1) >= 0).all()
    complete = [k for k in range(32) if k not in info["truncated"]]
    totals = m.profiles.sum(1)[complete]  # mm^3: level rise ~10.2 mm x 183,600 mm^2
    assert torch.all((totals > 1.8e6) & (totals < 1.95e6))
    placed = info["start_heights"]  # the default (ideal) rig: one rigid centroid explains the dips within 2 mm
    assert placed["centroid_rms_mm"] < 2.0 and info["geometry"]["pivot_mm"] == 0.0
    # first contact lies inside the grid: before smoothing the lowest slab holds at most
    # baseline noise (a quantum of 0.04 mm x 183,600 mm^2 = 7,344 mm^3), the next ones the object
    raw_profiles = read_raw_recording(cats_csv, grid, truncated="keep", smooth=False).profiles
    assert (raw_profiles[complete, 0] <= 0.04 * 183600 * 1.3).all() and (raw_profiles[complete, 1:3].sum(1) > 2e4).all()
    assert torch.allclose(raw_profiles.sum(1), m.profiles.sum(1))  # smoothing keeps the volume


def test_cats_symmetry_counts(cats_csv):
    grid = Grid(16, extent=360.0)
    m = read_raw_recording(cats_csv, grid, truncated="keep", symmetry={"n_fold": 3, "mirror": True})
    assert m.n_orientations == 7 * 18 + 1  # D3 images of tilt > 0 give 18 azimuths, tilt 0 one direction
    tilts = np.degrees(np.arccos(m.directions[:, 2].numpy()))
    assert np.isclose(tilts, 0).sum() == 1 and np.isclose(tilts, 35).sum() == 18
    m2 = read_raw_recording(cats_csv, grid, truncated="drop", symmetry={"n_fold": 3, "mirror": True},
                       interpolate={"n": 400, "k": 3, "max_angle_deg": 5})
    assert m2.metadata["interpolated_orientations"] > 0
    assert m2.metadata["recorded"]["measured_orientations"] == 32 - len(m2.metadata["recorded"]["truncated"])


# --------------------------------------------------------------------------- steps on simulated data
def test_symmetry_group_is_a_group():
    g = symmetry_group(3, mirror=True)
    assert g.shape == (6, 3, 3)
    assert np.allclose(np.einsum("gij,gkj->gik", g, g), np.eye(3))  # orthogonal
    products = np.einsum("aij,bjk->abik", g, g).reshape(-1, 3, 3)
    assert all(np.any(np.all(np.isclose(p, g), axis=(1, 2))) for p in products)  # closed
    assert len(symmetry_group(4)) == 4 and len(symmetry_group(1, mirror=True)) == 2


def test_expand_symmetry_matches_simulated_images():
    shape = three_balls()
    edges = np.linspace(-40, 40, 33)
    dirs = rig_to_direction([20.0, 40.0], [10.0, 75.0])
    _, m = simulate_measurement(shape, dirs, edges=edges, progress=False)
    group = symmetry_group(3, mirror=True)
    e = expand_symmetry(m, group)
    assert e.n_orientations == 12  # no image coincides
    _, truth = simulate_measurement(shape, e.directions, edges=edges, progress=False)
    assert torch.allclose(e.profiles, truth.profiles, atol=1e-6 * truth.profiles.max().item())
    # a direction on a mirror plane is its own mirror image: 3 distinct images, repeats averaged
    e2 = expand_symmetry(simulate_measurement(shape, rig_to_direction([30.0], [0.0]), edges=edges,
                                              progress=False)[1], group)
    assert e2.n_orientations == 3


def test_interpolate_orientations():
    shape = three_balls()
    edges = np.linspace(-40, 40, 33)
    dirs = fibonacci_hemisphere(60)
    _, m = simulate_measurement(shape, dirs, edges=edges, progress=False)
    targets = fibonacci_hemisphere(200)
    out = interpolate_orientations(m, targets, k=3, max_angle_deg=12.0)
    added = out.n_orientations - m.n_orientations
    assert added > 0 and torch.equal(out.profiles[:60], m.profiles)
    _, truth = simulate_measurement(shape, out.directions[60:], edges=edges, progress=False)
    err = (out.profiles[60:] - truth.profiles).abs().sum(1) / truth.profiles.sum(1)
    nearest = (out.directions[60:] @ m.directions.T).argmax(1)  # copying the nearest measured profile
    err_nearest = (m.profiles[nearest] - truth.profiles).abs().sum(1) / truth.profiles.sum(1)
    assert err.mean() < err_nearest.mean()
    assert torch.allclose(out.profiles[60:].sum(1), truth.profiles.sum(1), rtol=1e-6)  # volume kept
    far = interpolate_orientations(m, torch.tensor([[0.0, 0.0, 1.0]]), max_angle_deg=1e-3)
    assert far.n_orientations == m.n_orientations


def test_calibrate_cross_section_from_a_ball():
    ball = Ball(20.0)
    tank = Tank(cross_section_mm2=31415.0)
    raw = simulate_scan(ball, torch.tensor([[0.0, 0.0, 1.0]]), tank=tank, sensor=LevelSensor(quantum_mm=0.0),
                        protocol=DipProtocol(step_mm=2.0, clearance_mm=10.0, extra_steps=4), progress=False)
    area = calibrate_cross_section(raw.orientations[0], ball.volume)
    assert area == pytest.approx(31415.0, rel=1e-6)
    with pytest.raises(ValueError, match="did not rise"):
        calibrate_cross_section(np.full(10, 150.0), 1000.0)


def test_fixture_subtraction_recovers_object():
    obj, fixture = Ball(15.0, (0.0, 0.0, -10.0)), Box((4.0, 4.0, 15.0), (0.0, 0.0, 23.0))
    both = Union(obj, fixture)
    dirs = rig_to_direction([0.0, 20.0], [0.0, 0.0])
    tank, sensor = Tank(cross_section_mm2=8000.0), LevelSensor(quantum_mm=0.0)
    proto = DipProtocol(step_mm=1.0)

    def dip(shape, directions):
        # every shape dipped from the same stage origin: t_start fixed by the rig, not the shape
        raw = simulate_scan(Union(shape, Ball(1e-3, (0.0, 0.0, -39.0)), Ball(1e-3, (0.0, 0.0, 39.0))),
                            directions, tank=tank, sensor=sensor, protocol=proto, progress=False)
        return raw

    combined, fix, alone = dip(both, dirs), dip(fixture, dirs[:1]), dip(obj, dirs)
    fix.orientations[0].tilt_deg, fix.orientations[0].spin_deg = 0.0, 0.0
    for raw in (combined, alone):
        for o, (t, s) in zip(raw.orientations, [(0.0, 0.0), (20.0, 0.0)]):
            o.tilt_deg, o.spin_deg = t, s
    cleaned = subtract_fixture(combined, fix, n_baseline=2)
    edges = np.linspace(-40, 40, 41)
    a = preprocess(cleaned, edges=edges, t_start="metadata").profiles[0]
    b = preprocess(alone, edges=edges, t_start="metadata").profiles[0]
    assert torch.allclose(a, b, atol=0.02 * b.max().item())
    assert a.sum().item() == pytest.approx(obj.volume, rel=0.01)
    # a fixture recorded in another tank: its rises were read with the scan's section, the volume taken off scaled
    fix.header = dataclasses.replace(fix.header, tank_cross_section_mm2=16000.0)
    with pytest.raises(ValueError, match=r"fixture recording states a tank section of 16000 mm\^2, the scan 8000"):
        subtract_fixture(combined, fix, n_baseline=2)


def test_geometry_start_heights_recover_rig_geometry(tmp_path):
    """A scan from a rig with a pivot and a tilt-axis offset, its start height unknown: the geometry
    places every dip where the simulator had it, and the ideal rig cannot explain the centroids."""
    shape = three_balls(z=0.0)
    tilts = [0.0, 10.0, 20.0, 30.0, 30.0]
    truth_geometry = RigGeometry(pivot_mm=120.0, tilt_axis_offset_mm=10.0)
    dirs = rig_to_direction(tilts, [0.0, 0.0, 0.0, 0.0, 90.0])
    raw = simulate_scan(shape, dirs, tank=Tank(cross_section_mm2=10000.0), sensor=LevelSensor(quantum_mm=0.0),
                        protocol=DipProtocol(step_mm=1.0, clearance_mm=5.0, extra_steps=5),
                        geometry=truth_geometry, progress=False)
    truth = raw.header.t_start_mm + truth_geometry.height_shift(tilts)
    starts, info = geometry_start_heights(raw, 10000.0, truth_geometry, centre="centroid")
    assert np.allclose(starts, truth, atol=0.05) and info["centroid_rms_mm"] < 0.05
    _, ideal = geometry_start_heights(raw, 10000.0, RigGeometry(), centre="centroid")
    assert ideal["centroid_rms_mm"] > 1.0
    path = raw.save(tmp_path / "scan.jsonl")
    assert len(read_scan(path).orientations) == 5


def _cut_short(raw, ks, keep: float = 0.5):
    """``raw`` with the dips ``ks`` stopped after ``keep`` of their readings (still going under)."""
    for o in raw.orientations:
        if o.k in ks:
            n = int(keep * len(o.values))
            o.stage_mm, o.values, o.time_s, o.flags = o.stage_mm[:n], o.values[:n], o.time_s[:n], o.flags[:n]
    return raw


def test_a_scan_recorded_with_a_calibration_and_read_without_one_is_warned_about(tmp_path):
    """A scan made with ``scan.py +rig.calibration=FILE`` records the calibrated geometry; read without it, its dips
    were placed on the ideal rig without a word (the audit's torus, step scale 1.03 and tilt zero 2 deg: IoU 0.82
    instead of 0.94, ``consistent``)."""
    calibrated = RigGeometry(step_scale=1.03, tilt_zero_deg=2.0)
    raw = simulate_scan(Ball(20.0), fibonacci_hemisphere(6), tank=Tank(20000.0), geometry=calibrated, progress=False)
    raw.header.config.update({"rig_geometry": calibrated.to_dict(), "scan": {"rig": {"calibration": "rig_cal.yaml"}}})
    path = raw.save(tmp_path / "scan.jsonl")
    with pytest.warns(UserWarning, match=r"scan.jsonl was scanned with a rig geometry \(tilt_zero_deg=2, "
                                         r"step_scale=1.03; .*source.reader.calibration=rig_cal.yaml"):
        prepare_recording(path)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        prepare_recording(path, geometry=calibrated)  # given: nothing to say
        raw.header.config.pop("rig_geometry")
        prepare_recording(raw.save(tmp_path / "ideal.jsonl"))  # scanned on the ideal rig


def test_dropped_truncated_dips_are_named_counted_and_refused_when_most(tmp_path):
    """The audit's case: dips that ended before the object was under water were dropped with no word, and
    2 of 16 dips made an IoU-0.64 shape with exit 0. Now the drop is warned (naming the dips), counted in
    the metrics (``dips_truncated_dropped``), and refused when more than 75 % of the dips would go."""
    from dipnet.preprocessing.validation import validate_measurement

    grid = Grid(24, extent=80.0)
    raw = simulate_scan(Ball(20.0), fibonacci_hemisphere(8), progress=False)
    path = _cut_short(raw, {2, 5}).save(tmp_path / "two_short.jsonl")
    with pytest.warns(UserWarning, match=r"2 of 8 dips end before the object is under water \(dips 2, 5\)"):
        m = read_raw_recording(path, grid)
    assert m.n_orientations == 6
    assert validate_measurement(m, grid).metrics()["dips_truncated_dropped"] == 2
    assert validate_measurement(read_raw_recording(path, grid, truncated="keep"), grid).metrics()[
        "dips_truncated_dropped"] == 0
    raw = simulate_scan(Ball(20.0), fibonacci_hemisphere(8), progress=False)
    path = _cut_short(raw, set(range(7))).save(tmp_path / "most_short.jsonl")
    with pytest.raises(ValueError, match=r"7 of 8 dips end before .* more than 75%"):
        read_raw_recording(path, grid)


def test_incomplete_dips_left_out_are_counted_in_the_metrics(tmp_path):
    """The audit's case: a scan killed during its third dip was read as a 2-dip scan, the dip left out named
    only in the log; ``metrics.json`` now counts it (``dips_incomplete_dropped``) and names it."""
    from dipnet.preprocessing.validation import validate_measurement

    grid = Grid(24, extent=80.0)
    raw = simulate_scan(Ball(20.0), fibonacci_hemisphere(8), progress=False)
    raw.orientations[5].complete = False
    with pytest.warns(UserWarning, match=r"orientation\(s\) \[5\] are incomplete and left out"):
        m = read_raw_recording(raw.save(tmp_path / "killed.jsonl"), grid)
    metrics = validate_measurement(m, grid).metrics()
    assert m.n_orientations == 7 and metrics["dips_incomplete_dropped"] == 1
    assert metrics["validation"]["incomplete_dropped"] == [5]


def test_a_configured_tank_section_other_than_the_recordings_is_warned_and_recorded(tmp_path):
    """The audit's case: ``cross_section_mm2=26000`` on a scan whose header states 20,000 mm^2 silently scaled
    every slab by 1.3 (IoU 0.76 against 0.95, ``consistent``). Now a warning names both values, and the
    metrics record the section used; the recording's own value or a calibration's says nothing."""
    from dipnet.preprocessing.validation import validate_measurement

    grid = Grid(24, extent=80.0)
    path = simulate_scan(Ball(20.0), fibonacci_hemisphere(8), tank=Tank(20000.0), progress=False).save(
        tmp_path / "ball.jsonl")
    for options in ({"cross_section_mm2": 26000.0}, {"geometry": {"cross_section_mm2": 26000.0}}):
        m = read_raw_recording(path, grid, **options)
        with pytest.warns(UserWarning, match=r"the configured tank section 26000 mm\^2 replaces the 20000 mm\^2 "
                                             r"the recording states \(\+30%\)"):
            report = validate_measurement(m, grid)
        assert report.metrics()["validation"]["cross_section_mm2"] == {"used": 26000.0, "recorded": 20000.0,
                                                                      "configured": 26000.0}
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for options in ({}, {"cross_section_mm2": 20000.0}):
            report = validate_measurement(read_raw_recording(path, grid, **options), grid)
            assert report.metrics()["validation"]["cross_section_mm2"]["used"] == 20000.0


def test_a_recording_on_a_grid_of_the_other_dimension_is_refused_before_its_readings_are_repaired(tmp_path):
    """Before: a 3D torus scan read with ndim=2 "repaired" 7 of its clean readings (against the 2D grid's rise cap),
    each with a warning, and then was refused as "3D directions for a 2D grid"."""
    import warnings

    path = simulate_scan(Ball(20.0), fibonacci_hemisphere(8), progress=False).save(tmp_path / "ball.jsonl")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no repair warning comes first
        with pytest.raises(ValueError, match=r"ball.jsonl: a 3D recording \(its header's ndim\) for a 2D grid: "
                                             r"set ndim=3"):
            read_raw_recording(path, Grid(16, ndim=2, extent=80.0))


def test_a_csv_with_its_angles_in_radians_is_warned_about(tmp_path, recwarn):
    """Before: R1_deg, R2_deg given in radians were read as degrees without a word (the dips bunched within 0.6 deg
    of the vertical; exit 0, only the dips' disagreement warned). Now a warning names the columns and the unit;
    the authors' own whole-degree file is not warned about."""
    lines = CSV.read_text().splitlines()
    rows = [line.split(",") for line in lines[1:]]
    radians = [lines[0]] + [",".join([f[0], f"{math.radians(float(f[1])):.6f}", f"{math.radians(float(f[2])):.6f}",
                                      *f[3:]]) for f in rows]
    path = tmp_path / "rad.csv"
    path.write_text("\n".join(radians) + "\n")
    with pytest.warns(UserWarning, match=r"rad.csv: every R1_deg and R2_deg lies within \[-2 pi, 2 pi\] \(R1 0 to "
                                         r"0.610865, R2 0 to 1.0472\), and not in whole degrees: angles in radians\?"):
        assert len(read_authors_csv(path).orientations) == 32
    read_authors_csv(CSV)
    assert not [w for w in recwarn if "radians" in str(w.message)]


def test_a_csv_dip_whose_level_never_rises_is_named_by_its_angles_and_rows(tmp_path):
    """Before: "flat.csv: orientation 1: the reading never rises", a 0-based index the CSV does not hold. Now the
    dip's R1, R2 and SN rows, its readings' count and range, and what to do."""
    lines = CSV.read_text().splitlines()
    rows = [line.split(",") for line in lines[1:]]
    flat = [lines[0]] + [",".join(f[:4] + [rows[111][4]] if 111 <= i < 222 else f) for i, f in enumerate(rows)]
    path = tmp_path / "flat.csv"
    path.write_text("\n".join(flat) + "\n")
    from dipnet.preprocessing.recorded import AUTHORS_TANK_MM2, profile_centroids
    with pytest.raises(ValueError, match=r"orientation 1 \(tilt 0, spin 20 deg, SN 112-222\): the reading never "
                                         r"rises \(111 reading\(s\), all 188.56\): the object never reached the "
                                         r"water.*remove the dip's rows"):
        profile_centroids(read_authors_csv(path), AUTHORS_TANK_MM2)


def test_a_csv_counting_depth_as_positive_is_named_so(tmp_path):
    """Before: the authors' CSV with its Height_mm negated (depth counted as positive) was refused as a stage that
    "moved backwards within a dip (rows out of order? ...)", which every dip does alike. Now the sign is named."""
    lines = CSV.read_text().splitlines()
    flipped = [lines[0]] + [",".join(f[:3] + [str(-float(f[3])), f[4]])
                            for f in (line.split(",") for line in lines[1:])]
    path = tmp_path / "depth.csv"
    path.write_text("\n".join(flipped) + "\n")
    with pytest.raises(RawScanFileError, match=r"depth.csv: Height_mm rises within every dip \(25, 28, \.\.\.\).*"
                                               r"counts depth as positive; negate its Height_mm column"):
        read_scan(path)
    assert len(read_scan(CSV).orientations) == 32


def test_readings_are_repaired_with_the_geometrys_drift_taken_out(tmp_path):
    """A recording's readings were repaired (and its truncated dips found) before its
    geometry's level drift was taken out, so a drift over the rest readings larger than the noise passed for
    outliers: of 8 dips of a hammer (2,000 mm^3 in an 84,000 mm^2 tank, -3e-5 mm/s) read with that drift, 3 were
    kept, where the same scan without the drift keeps 7. Now the drifting scan keeps the same 7."""
    from dipnet.preprocessing.datasets import mesh_path
    from dipnet.shapes import load_mesh

    kept = {}
    for drift in (0.0, -3e-5):
        rig = RigGeometry(pivot_mm=-120.0, tilt_axis_offset_mm=30.0, level_drift_mm_per_s=drift)
        raw = simulate_scan(load_mesh(mesh_path("hammer"), radius=40.0), fibonacci_hemisphere(8), tank=Tank(84000.0),
                            geometry=rig, sensor=LevelSensor(snr_db=30.0, seed=1), progress=False)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            scan, _, info = prepare_recording(raw.save(tmp_path / f"drift{drift}.jsonl"), geometry=rig)
        kept[drift] = [o.k for o in scan.orientations]
        assert not info["readings"]["rejected"]
    assert kept[-3e-5] == kept[0.0] and len(kept[0.0]) >= 7


def test_a_calibration_file_for_a_2d_recording_is_refused_naming_the_option(tmp_path):
    """Before: a 3D rig's calibration file on a 2D scan was refused as "orientation 0 has no rig angles: the rotary-axis
    geometry cannot apply" (its pivot not 0) or "a profile holds 5.655e+05 mm^2, more than the working ball's ...:
    wrong units or scale, or increase extent_mm" (its section of 60000 mm^2 taken for the 2D tank's width), naming
    neither the file nor the option."""
    from dipnet.core.calibration_file import Calibration, save_calibration
    from dipnet.core.orientations import angles_2d, directions_2d
    from dipnet.shapes import Disk

    path = simulate_scan(Disk(20.0), directions_2d(angles_2d(8)), progress=False).save(tmp_path / "disk.jsonl")
    for geometry in (RigGeometry(cross_section_mm2=60000.0), RigGeometry(pivot_mm=20.0, cross_section_mm2=60000.0)):
        cal = save_calibration(Calibration(geometry, rig="dipnet.simulator", tank="t1"), tmp_path / "cal.yaml")
        with pytest.raises(ValueError, match=r"disk.jsonl: a 2D recording .* rig calibration file .*cal.yaml "
                                             r"\(source.reader.calibration\)"):
            read_raw_recording(path, Grid(16, ndim=2, extent=80.0), calibration=cal)
    read_raw_recording(path, Grid(16, ndim=2, extent=80.0))  # without one it reads


def test_rotary_geometry_values_for_a_2d_recording_are_refused_naming_the_options(tmp_path):
    """Before: ``ndim=2 source.reader.geometry.pivot_mm=20`` was refused as "orientation 0 has no rig angles: the
    rotary-axis geometry cannot apply", naming no option."""
    from dipnet.core.orientations import angles_2d, directions_2d
    from dipnet.shapes import Disk

    path = simulate_scan(Disk(20.0), directions_2d(angles_2d(8)), progress=False).save(tmp_path / "disk.jsonl")
    with pytest.raises(ValueError, match=r"disk.jsonl: a 2D recording .* \(source.reader.geometry.pivot_mm=20, "
                                         r"source.reader.geometry.tilt_zero_deg=1.5\) to move: leave them 0"):
        read_raw_recording(path, Grid(16, ndim=2, extent=80.0), geometry={"pivot_mm": 20.0, "tilt_zero_deg": 1.5})
    read_raw_recording(path, Grid(16, ndim=2, extent=80.0), geometry={"step_scale": 1.01})  # applies in 2D


@pytest.mark.parametrize(("options", "message"), [
    ({"tail_fraction": 0}, r"tail_fraction \(source.reader.tail_fraction\) must be a fraction in \(0, 1\]"),
    ({"tail_fraction": -1}, r"source.reader.tail_fraction"),
    ({"tail_fraction": 2.0}, r"source.reader.tail_fraction"),
    ({"tail_fraction": "abc"}, r"source.reader.tail_fraction"),
    ({"tail_tol": math.nan}, r"tail_tol \(source.reader.tail_tol\) must be a fraction in \(0, 1\)"),
    ({"tail_tol": math.inf}, r"source.reader.tail_tol"),
    ({"tail_tol": 2.0}, r"source.reader.tail_tol"),
    ({"tail_tol": True}, r"source.reader.tail_tol"),
    ({"tail_tol": 0}, r"source.reader.tail_tol"),
    ({"interpolate": {"n": 100, "max_angle_deg": -1}}, r"source.reader.interpolate.max_angle_deg must be an angle"),
    ({"interpolate": {"n": 100, "max_angle_deg": math.nan}}, r"source.reader.interpolate.max_angle_deg"),
    ({"interpolate": {"n": 100, "k": 0}}, r"source.reader.interpolate.k must be a whole number >= 1"),
    ({"interpolate": {"n": 2.5}}, r"source.reader.interpolate.n must be a whole number"),
    ({"interpolate": {"bogus": 1}}, r"interpolate \(source.reader.interpolate\) takes n"),
    ({"interpolate": 5}, r"interpolate \(source.reader.interpolate\) must be null or"),
    ({"fixture": 5}, r"fixture \(source.reader.fixture\) must be a fixture-only recording's file"),
    ({"fixture": "."}, r"source.reader.fixture.* \(a folder\)"),
    ({"geometry": 5}, r"geometry \(source.reader.geometry\) must be a mapping"),
])
def test_reader_options_out_of_range_are_refused_naming_the_option(tmp_path, options, message):
    """Before: ``tail_tol`` NaN, inf or 2 (and ``tail_fraction`` 0 or -1) read every still-rising dip as complete,
    ``interpolate.max_angle_deg=-1`` or NaN added no direction, ``interpolate.k=0`` interpolated from 0 neighbours,
    all without a word; ``tail_fraction=2`` raised an ``IndexError``, ``interpolate={bogus: 1}`` a ``KeyError: 'n'``,
    ``fixture=5`` and ``geometry=5`` a ``TypeError``, naming no option. Each is now refused before the file is read."""
    path = tmp_path / "missing.jsonl"  # never read: the options are refused first
    with pytest.raises(ValueError, match=message):
        read_raw_recording(path, Grid(16, extent=80.0), **options)
