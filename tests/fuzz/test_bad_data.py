"""Issue 13's bad-data scenarios: glitched readings are repaired, impossible data refused, every
user error one line naming the file (and line) or option with exit code 2."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_module

from dipnet.preprocessing.datasets import CATS_CSV
from dipnet.core.grid import Grid
from dipnet.core.measurement import DipMeasurement
from dipnet.core.orientations import make_directions
from dipnet.preprocessing.preprocess import preprocess
from dipnet.core.rawscan import RawScanFileError, read_rawscan
from dipnet.preprocessing.readings import outlier_mask, repair_readings
from dipnet.core.memory import ResourceError
from dipnet.jobs.resources import check_memory, estimate_memory
from dipnet.preprocessing.recorded import read_scan
from dipnet.shapes import ShapeError, builtin_shape, load_mesh
from dipnet.simulator.simulate import simulate_measurement
from dipnet.preprocessing.sources import read_recorded
from dipnet.preprocessing.validation import MeasurementValidationError, validate_measurement
from script_runs import one_line_error

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "reconstruct.py"
GRID = Grid(16, 3, 100.0)
CATS_GRID = Grid(16, 3, 360.0)
CATS_OPTIONS = dict(cross_section_mm2=183600.0, geometry={"pivot_mm": 188.0, "tilt_axis_offset_mm": -18.0},
                    truncated="keep", smooth=True)


# ----------------------------------------------------------------------------- helpers
def _csv_with(tmp_path: Path, name: str, sn: int, column: int, text: str) -> Path:
    """The cats CSV with field ``column`` of the row ``SN = sn`` (file line ``sn + 1``) set to ``text``."""
    lines = CATS_CSV.read_text().splitlines()
    fields = lines[sn].split(",")
    assert int(fields[0]) == sn
    fields[column] = text
    lines[sn] = ",".join(fields)
    path = tmp_path / name
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.fixture(scope="module")
def cats_clean() -> DipMeasurement:
    return read_recorded(str(CATS_CSV), CATS_GRID, **CATS_OPTIONS)


@pytest.fixture(scope="module")
def scan_file(tmp_path_factory) -> Path:
    """A simulated raw scan (the chamber box, 6 dips, 1 mm steps, noise-free) saved as ``.jsonl``."""
    shape = builtin_shape("chamber_box", 3, 0.9 * GRID.radius)
    raw, _ = simulate_measurement(shape, make_directions("fibonacci", 6, 3, 0), grid=GRID, progress=False)
    return raw.save(tmp_path_factory.mktemp("scan") / "rawscan.jsonl")


def _edit_jsonl(src: Path, dst: Path, edit) -> Path:
    rows = [json.loads(line) for line in src.read_text().splitlines()]
    dst.write_text("\n".join(json.dumps(r) for r in edit(rows)) + "\n")
    return dst


def _middle_reading(rows: list[dict], k: int = 0) -> int:
    """Index of the reading half way through dip ``k``'s rise."""
    values = [(i, r["value"]) for i, r in enumerate(rows) if r["type"] == "reading" and r["k"] == k]
    lo, hi = values[0][1], values[-1][1]
    return min(values, key=lambda iv: abs(iv[1] - 0.5 * (lo + hi)))[0]


def _cli_subprocess(tmp_path: Path, *overrides: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), f"hydra.run.dir={tmp_path}", "output.progress=false",
                           *overrides], capture_output=True, text=True, timeout=300)


@pytest.fixture
def cli(script_run):
    """``_cli_subprocess`` in this process (tests/script_runs.py: the same exit code and output, without the
    ~6 s a subprocess spends importing torch); one test below keeps the real subprocess."""
    return lambda run_dir, *overrides: script_run("reconstruct", run_dir, "output.progress=false", *overrides)


# ----------------------------------------------------------------------------- item 1: robust readings
@pytest.mark.parametrize("value", ["1e9", "250"])
def test_csv_spike_at_row_60_is_repaired(tmp_path, cats_clean, value):
    """Before: 1e9 at SN 60 gave measured volume 0, 250 removed 18% of the reconstruction."""
    path = _csv_with(tmp_path, "spike.csv", 60, 4, value)
    with pytest.warns(UserWarning, match="repaired 1 outlier reading"):
        m = read_recorded(str(path), CATS_GRID, **CATS_OPTIONS)
    report = m.metadata["readings"]
    assert report["readings_repaired"] == 1 and report["dips_rejected"] == 0
    assert report["repaired"][0]["value"] == float(value) and report["repaired"][0]["k"] == 0
    clean = cats_clean.profiles.sum(1)
    np.testing.assert_allclose(m.profiles.sum(1), clean, rtol=0.01)
    assert m.volume_estimate() == pytest.approx(cats_clean.volume_estimate(), rel=0.01)


@pytest.mark.parametrize("value", [1e6, 160.0])
def test_jsonl_spike_is_repaired(tmp_path, scan_file, value):
    """One reading set to 1e6 (or 160 mm where the level is ~151 mm) no longer changes the dip."""
    clean = read_recorded(str(scan_file), GRID, t_start="metadata")
    rows = [json.loads(line) for line in scan_file.read_text().splitlines()]
    i = _middle_reading(rows)

    def spike(rows):
        rows[i]["value"] = value
        return rows

    path = _edit_jsonl(scan_file, tmp_path / "spike.jsonl", spike)
    with pytest.warns(UserWarning, match="repaired 1 outlier reading"):
        m = read_recorded(str(path), GRID, t_start="metadata")
    assert m.metadata["readings"]["repaired"][0]["value"] == value
    np.testing.assert_allclose(m.profiles.sum(1), clean.profiles.sum(1), rtol=0.01)
    assert torch.linalg.norm(m.profiles[0] - clean.profiles[0]) < 0.01 * torch.linalg.norm(clean.profiles[0])
    # without the repair the monotone fit carries the spike: the dip's profile is wrecked
    unrepaired = preprocess(read_rawscan(path), grid=GRID, t_start="metadata", repair=False)
    assert torch.linalg.norm(unrepaired.profiles[0] - clean.profiles[0]) > 0.5 * torch.linalg.norm(clean.profiles[0])


def test_outlier_rule():
    rng = np.random.default_rng(0)
    stage = np.arange(100.0)
    level = 150.0 + 0.02 * np.clip(stage - 30, 0, 40)  # flat, rising 0.02 mm/mm, flat
    noisy = level + rng.normal(0, 0.003, stage.size)
    assert not outlier_mask(stage, noisy, 0.003)[0].any()  # clean noisy dips: no false alarm
    burst = noisy.copy()
    burst[50:53] = 160.0  # three consecutive spikes: the neighbour median cannot see them, the range test can
    assert outlier_mask(stage, burst, 0.003)[0][50:53].all()
    drop = noisy.copy()
    drop[60] -= 0.2  # a drop 10x the per-step rise
    assert np.flatnonzero(outlier_mask(stage, drop, 0.003)[0]).tolist() == [60]


def test_too_many_outliers_reject_the_dip(scan_file):
    raw = read_rawscan(scan_file)
    o = raw.orientations[1]
    o.values[5::6] += 50.0  # one reading in six
    with pytest.warns(UserWarning, match="rejected 1 dip"):
        fixed, report = repair_readings(raw)
    assert [r["k"] for r in report.rejected] == [1] and "outliers" in report.rejected[0]["reason"]
    assert [o.k for o in fixed.orientations] == [0, 2, 3, 4, 5]


def test_stage_out_of_order_names_file_and_line(tmp_path, scan_file):
    rows = [json.loads(line) for line in scan_file.read_text().splitlines()]
    at = {r["stage_mm"]: i for i, r in enumerate(rows) if r["type"] == "reading" and r["k"] == 0}

    def swap(rows):  # stage 40 recorded before stage 30
        rows[at[30.0]], rows[at[40.0]] = rows[at[40.0]], rows[at[30.0]]
        return rows

    path = _edit_jsonl(scan_file, tmp_path / "swap.jsonl", swap)
    with pytest.raises(RawScanFileError, match=rf"swap.jsonl:{at[30.0] + 2}: orientation 0: .*moved backwards"):
        read_rawscan(path)
    back = _csv_with(tmp_path, "back.csv", 60, 3, "-190")  # Height goes up from -199 to -190
    with pytest.raises(RawScanFileError, match=r"back.csv:61: Height_mm -190 after -199.*moved backwards"):
        read_scan(back)


def test_quantity_contradicting_the_recording_is_refused(tmp_path, scan_file):
    def as_mass(rows):
        rows[0]["quantity"] = "mass_g"
        return rows

    path = _edit_jsonl(scan_file, tmp_path / "mass.jsonl", as_mass)
    with pytest.raises(RawScanFileError, match=r"mass.jsonl:1: quantity 'mass_g' is read in g but .* 'mm'"):
        read_rawscan(path)

    def as_mass_no_units(rows):
        rows[0].update(quantity="mass_g", units=None)
        return rows

    path = _edit_jsonl(scan_file, tmp_path / "mass2.jsonl", as_mass_no_units)
    with pytest.raises(RawScanFileError, match="recording sensor's quantity 'level_mm'"):
        read_rawscan(path)


def test_nan_in_csv_names_file_and_line(tmp_path):
    path = _csv_with(tmp_path, "nan.csv", 60, 4, "nan")
    with pytest.raises(RawScanFileError, match=r"nan.csv:61: WaterLevel_mm is not a finite number"):
        read_scan(path)


def test_truncated_last_line_warns_and_header_only_is_refused(tmp_path, scan_file):
    lines = scan_file.read_text().splitlines()
    cut = tmp_path / "cut.jsonl"
    cut.write_text("\n".join(lines[:-2] + [lines[-2][:20]]))
    with pytest.warns(UserWarning, match=r"last line is truncated.*orientation\(s\) \[5\] are incomplete"):
        m = read_recorded(str(cut), GRID, t_start="metadata")
    assert m.n_orientations == 5
    header_only = tmp_path / "header.jsonl"
    header_only.write_text(lines[0] + "\n")
    with pytest.raises(RawScanFileError, match=r"scan .*header.jsonl holds no complete dip"):
        read_recorded(str(header_only), GRID, t_start="metadata")


# ----------------------------------------------------------------------------- item 2: validation
@pytest.fixture(scope="module")
def measurement(scan_file) -> DipMeasurement:
    return read_recorded(str(scan_file), GRID, t_start="metadata")


def _with(m: DipMeasurement, profiles, directions=None) -> DipMeasurement:
    d = m.directions if directions is None else directions
    return DipMeasurement(d, profiles, m.slab_thickness, torch.full((len(d),), float(m.offsets[0])), None,
                          {"path": "case.npz"})


def test_negative_and_huge_profiles_are_refused(measurement):
    with pytest.raises(MeasurementValidationError, match=r"case.npz: profile \d sums to -.*negative"):
        validate_measurement(_with(measurement, -measurement.profiles), GRID)
    with pytest.raises(MeasurementValidationError, match=r"case.npz: a profile holds \d\.\d+e\+30\d mm\^3, more than"):
        validate_measurement(_with(measurement, measurement.profiles * 1e300), GRID)
    noisy = measurement.profiles.clone()
    noisy[:, 0] = -1e-3 * noisy.max()  # a small negative from noise is tolerated
    report = validate_measurement(_with(measurement, noisy), GRID)
    assert report.stats["negative_slabs"] == measurement.n_orientations and not report.warnings


def test_ten_identical_directions_with_different_profiles_warn(measurement):
    scale = torch.linspace(0.7, 1.3, 10, dtype=torch.float64)[:, None]
    ten = _with(measurement, measurement.profiles[:1] * scale, measurement.directions[:1].repeat(10, 1))
    with pytest.warns(UserWarning) as record:
        report = validate_measurement(ten, GRID)
    messages = [str(w.message) for w in record]
    assert any(re.search(r"45 of 45 pair\(s\) of directions within 0.5 deg measure different profiles", m)
               for m in messages)
    assert any(re.search(r"8 of 10 dip total\(s\) differ from the median", m) for m in messages)
    assert report.stats["duplicate_max_discrepancy"] == pytest.approx(0.6)
    assert report.stats["total_spread"] == pytest.approx(0.6, rel=1e-6)
    consistent = validate_measurement(measurement, GRID)  # distinct directions, equal totals: silent
    assert not consistent.warnings and consistent.stats["total_spread"] < 1e-6
    assert consistent.metrics()["readings_repaired"] == 0 and "validation" in consistent.metrics()


# ----------------------------------------------------------------------------- items 3, 4: sizes and errors
def test_memory_estimate_refuses_huge_grids():
    with initialize_config_module(config_module="dipnet.conf", version_base="1.3"):
        huge = compose(config_name="config", overrides=["resolution=100000"])
        large = compose(config_name="config", overrides=["resolution=1000"])
        small = compose(config_name="config", overrides=["resolution=16", "n_dips=8"])
    with pytest.raises(ResourceError, match=r"resolution=100000 .* needs ~\d+ PB .* this machine has 23 GB available"):
        check_memory(huge, available=23 * 10**9)
    assert check_memory(small, available=23 * 10**9).total < 10**7
    # the estimate grows like N^3 once the voxel terms dominate
    assert estimate_memory(huge).total / estimate_memory(large).total == pytest.approx(1e6, rel=0.01)


def test_garbage_stl_names_the_file(tmp_path):
    path = tmp_path / "garbage.stl"
    path.write_bytes(bytes(np.random.default_rng(0).integers(0, 256, 4000, dtype=np.uint8)))
    with pytest.raises(ShapeError, match=r"garbage.stl: corrupt, or not a mesh format") as info:
        load_mesh(path)
    assert "charset" not in str(info.value)


@pytest.mark.parametrize("overrides,message", [
    (["solver=foo"], r"error: In 'config': Could not find 'solver/foo' Available options in 'solver': .*implicit"),
    # source=recorded without its path ("error: option source.reader.path is required"): the real process below
    (["resolution=100000"], r"error: resolution=100000 \(ndim=3, n_dips=120\) needs ~\d+ PB"),
])
def test_cli_errors_are_one_line_with_exit_2(tmp_path, cli, overrides, message):
    line = one_line_error(cli(tmp_path, *overrides))
    assert re.match(message, line), line


def test_cli_error_of_the_real_process_is_one_line_with_exit_2(tmp_path):
    """The cases above run the script in this process; here the process itself (its exit code 2), on the third
    case: a required option left unset."""
    line = one_line_error(_cli_subprocess(tmp_path, "source=recorded"))
    assert line == "error: option source.reader.path is required: set it on the command line, e.g. " \
                   "source.reader.path=...", line


# ----------------------------------------------------------------------------- issue 22: messages
def test_nan_sigma_in_a_measurement_names_the_file_and_the_array(tmp_path, scan_file, cli):
    """Before: NaN noise reached the solver; the message named neither the file nor the array."""
    m = preprocess(read_rawscan(scan_file), grid=GRID)
    valid = DipMeasurement(m.directions, m.profiles, m.slab_thickness, m.offsets, torch.full_like(m.profiles, 50.0))
    with np.load(valid.save(tmp_path / "valid.npz")) as data:
        arrays = {k: data[k] for k in data.files}
    arrays["sigma"][2, 5] = np.nan
    path = tmp_path / "nan.npz"
    np.savez(path, **arrays)
    line = one_line_error(cli(tmp_path / "run", "source=recorded", f"source.reader.path={path}"))
    assert line == (f"error: {path}: measurement array 'sigma' holds 1 NaN or infinite value(s) of "
                    f"{m.profiles.numel()}"), line


@pytest.mark.parametrize("encoding", ["utf-8-sig", "utf-16"])
def test_csv_saved_by_a_spreadsheet_is_read_as_the_original(tmp_path, cli, encoding):
    """Before: the byte-order mark spreadsheet programs write first was refused as a header "���SN,..."."""
    path = tmp_path / "cats.csv"
    path.write_bytes(CATS_CSV.read_text().replace("\n", "\r\n").encode(encoding))
    # 450 mm: placed by their centroids on the ideal rig, the cats reach 175 mm from the centre (a 360 mm grid's
    # working ball at 16^3 has a radius of 157.5 mm, and is refused)
    proc = cli(tmp_path / "run", "source=recorded", f"source.reader.path={path}", "extent_mm=450", "resolution=16",
                "+source.reader.t_start=centroid", "source.reader.truncated=keep", "output.figures=false",
                "output.uncertainty=false", "output.resolvability=false")
    assert proc.returncode == 0, proc.stderr[-2000:]
    original = read_recorded(str(CATS_CSV), Grid(16, 3, 450.0), t_start="centroid", truncated="keep")
    torch.testing.assert_close(DipMeasurement.load(tmp_path / "run" / "measurement.npz").profiles, original.profiles)


# ----------------------------------------------------------------------------- issue 22: units
def _in_units(rows: list[dict], stage: str, value: str, factor_stage: float, factor_value: float) -> list[dict]:
    """The scan with its stage and level columns re-expressed (divided by the factors) and declared."""
    rows[0]["units"].update(stage=stage, value=value)
    rows[0]["step_mm"] /= factor_stage
    for r in rows[1:]:
        if r["type"] == "reading":
            r["stage_mm"] /= factor_stage
            r["value"] /= factor_value
    return rows


def _measured_volume(proc: subprocess.CompletedProcess, run_dir: Path) -> float:
    assert proc.returncode == 0, proc.stderr
    return json.loads((run_dir / "metrics.json").read_text())["measured_volume_mm3"]


@pytest.mark.slow
def test_declared_units_are_honoured(tmp_path, scan_file, cli):
    inches = _edit_jsonl(scan_file, tmp_path / "inches.jsonl", lambda rows: _in_units(rows, "in", "cm", 25.4, 10.0))
    quiet = ("source=recorded", "resolution=16", "extent_mm=100", "output.figures=false", "output.uncertainty=false",
             "output.resolvability=false", "+source.reader.t_start=metadata")
    reference = _measured_volume(cli(tmp_path / "mm", *quiet, f"source.reader.path={scan_file}"), tmp_path / "mm")
    converted = _measured_volume(cli(tmp_path / "in", *quiet, f"source.reader.path={inches}"), tmp_path / "in")
    assert converted == pytest.approx(reference, rel=1e-9)
    assert read_rawscan(inches).orientations[0].stage_mm == \
        pytest.approx(read_rawscan(scan_file).orientations[0].stage_mm)


@pytest.mark.parametrize("units,message", [
    ({"stage": "furlong"}, r"units.stage: unknown unit 'furlong'; stage is read in one of mm, cm, m, in"),
    ({"value": "psi"}, r"quantity 'level_mm' is read in mm but the header's units say readings are in 'psi'"),
    ({"pressure": "Pa"}, r"units.pressure: no such field"),
])
def test_unknown_units_are_refused_naming_the_field(tmp_path, scan_file, cli, units, message):
    path = _edit_jsonl(scan_file, tmp_path / "odd.jsonl", lambda rows: [{**rows[0], "units": units}, *rows[1:]])
    line = one_line_error(cli(tmp_path / "run", "source=recorded", f"source.reader.path={path}"))
    assert re.search(rf"error: {re.escape(str(path))}:1: {message}", line), line


def test_a_level_counted_downwards_is_named_so(tmp_path, scan_file, cli):
    """The audit's case: levels with their sign reversed (300 - level) had each dip rejected for its "outliers",
    and then the scan for having no dip left. The reading falls as the object goes down: that is named."""
    def reverse(rows):
        return [{**r, "value": 300.0 - r["value"]} if r["type"] == "reading" else r for r in rows]

    path = _edit_jsonl(scan_file, tmp_path / "reversed.jsonl", reverse)
    line = one_line_error(cli(tmp_path / "run", "source=recorded", f"source.reader.path={path}", "extent_mm=100",
                              "resolution=16"))
    assert line.startswith(f"error: {path}: column value (of the reading lines): the reading falls as the object is "
                           "lowered in 6 of 6 dips"), line
    assert "is its sign reversed" in line, line


@pytest.mark.slow
def test_levels_in_metres_under_a_mm_header_are_refused(tmp_path, cli):
    lines = CATS_CSV.read_text().splitlines()
    metres = [lines[0]] + [",".join([*row.split(",")[:4], f"{float(row.split(',')[4]) / 1000:.5f}"])
                           for row in lines[1:]]
    path = tmp_path / "cats_metres.csv"
    path.write_text("\n".join(metres) + "\n")
    line = one_line_error(cli(tmp_path / "run", "experiment=cats_real", f"source.reader.path={path}"))
    assert line.startswith(f"error: {path}: column WaterLevel_mm: the water levels are at most 0.199 mm"), line
    # levels in metres are no multiples of the recording's 0.04 mm steps, so the reader claims no sensor resolution
    # for them (it once did: "below the sensor resolution 0.04 mm")
    assert "look like metres (199 mm)" in line and "sensor resolution" not in line, line
