"""Fuzz tests for every reader: a mutated file gives the one-line user error or a valid measurement.

For each reader (mesh files, ``.npz`` measurements, ``.jsonl`` raw scans, the authors' CSV) a
small valid sample file is mutated in seeded ways (truncation, byte flips, NaN/inf, huge and
negative values, wrong types, missing keys, shuffled and duplicated lines, an empty file,
binary garbage). Every case must either

* raise a user error (``ValueError`` / ``FileNotFoundError`` subclass) whose one-line message
  (:func:`dipnet.jobs.cli.error_message`) names the file, or
* yield a measurement that :func:`dipnet.preprocessing.validation.validate_measurement` accepts.

Any other exception (``TypeError``, ``IndexError``, ``ImportError``...) fails the test.

Rig calibration files are fuzzed as applied to a valid raw scan: the error must name the
calibration file. Extension point: a new reader adds one :class:`Reader` to :data:`READERS`: a
builder writing a valid sample file and a function reading a file into a
:class:`~dipnet.core.measurement.DipMeasurement` on :data:`GRID` (or raising the user error).
"""

from __future__ import annotations

import json
import re
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from dipnet.jobs.cli import error_message
from dipnet.preprocessing.datasets import CATS_CSV
from dipnet.core.grid import Grid
from dipnet.core.measurement import DipMeasurement
from dipnet.core.orientations import make_directions
from dipnet.simulator.physics import LevelSensor
from dipnet.core.calibration_file import Calibration, save_calibration
from dipnet.core.geometry import RigGeometry
from dipnet.preprocessing.sources import read_recorded
from dipnet.shapes import Ball, load_mesh
from dipnet.simulator.simulate import simulate_measurement
from dipnet.preprocessing.validation import validate_measurement

GRID = Grid(16, 3, 100.0)
CSV_GRID = Grid(16, 3, 450.0)  # the cats placed by their centroids need a larger working ball than 360 mm gives at 16^3
DIRECTIONS = make_directions("fibonacci", 4, 3, 0)
SEEDS = range(2)
NUMBER = re.compile(rb"-?\d+\.?\d*(?:[eE][-+]?\d+)?")


BYTE_MUTATIONS = ("truncated", "byte_flips", "empty", "garbage")


@dataclass(frozen=True)
class Reader:
    """One reader under test: ``build(dir) -> sample path``, ``read(path) -> DipMeasurement`` and
    the names of the :data:`MUTATIONS` that apply to its format (default: all)."""

    name: str
    suffix: str
    build: Callable[[Path], Path]
    read: Callable[[Path], DipMeasurement]
    mutations: tuple[str, ...] | None = None


# ----------------------------------------------------------------------------- the readers
def _build_stl(tmp: Path) -> Path:
    path = tmp / "sample.stl"
    trimesh.creation.icosphere(subdivisions=1, radius=30.0).export(path)  # binary STL
    return path


def _build_ply(tmp: Path) -> Path:
    path = tmp / "sample.ply"
    trimesh.creation.icosphere(subdivisions=1, radius=30.0).export(path, encoding="ascii")
    return path


def _read_mesh(path: Path) -> DipMeasurement:
    shape = load_mesh(path, radius=0.8 * GRID.radius)
    return simulate_measurement(shape, DIRECTIONS, grid=GRID, progress=False)[1]


def _simulated(tmp: Path):
    return simulate_measurement(Ball(30.0), DIRECTIONS, grid=GRID,
                                sensor=LevelSensor(sigma_mm=0.002, quantum_mm=0.001), step_mm=4.0, progress=False)


def _build_npz(tmp: Path) -> Path:
    return _simulated(tmp)[1].save(tmp / "sample.npz")


def _build_jsonl(tmp: Path) -> Path:
    return _simulated(tmp)[0].save(tmp / "sample.jsonl")


def _build_csv(tmp: Path) -> Path:
    lines = CATS_CSV.read_text().splitlines()
    path = tmp / "sample.csv"
    path.write_text("\n".join(lines[:1] + lines[1:1 + 2 * 111]) + "\n")  # two dips of the real recording
    return path


def _read_csv(path: Path) -> DipMeasurement:
    return read_recorded(str(path), CSV_GRID, t_start="centroid", truncated="keep")


_CALIBRATED_SCAN: dict[str, Path] = {}  # the raw scan the calibration files are applied to


def _build_calibration(tmp: Path) -> Path:
    raw = _simulated(tmp)[0]
    _CALIBRATED_SCAN["path"] = raw.save(tmp / "calibrated.jsonl")
    geometry = RigGeometry(pivot_mm=5.0, tilt_axis_offset_mm=1.0, cross_section_mm2=raw.header.tank_cross_section_mm2)
    return save_calibration(Calibration(geometry, rig=raw.header.rig, tank="tank-1", method="reference",
                                        uncertainty={"pivot_mm": 0.3}), tmp / "sample.yaml")


def _read_calibrated(path: Path) -> DipMeasurement:
    return read_recorded(str(_CALIBRATED_SCAN["path"]), GRID, t_start="metadata", calibration=path)


READERS = [
    Reader("mesh_stl", ".stl", _build_stl, _read_mesh, BYTE_MUTATIONS),
    Reader("mesh_ply", ".ply", _build_ply, _read_mesh),
    Reader("npz", ".npz", _build_npz, lambda p: read_recorded(str(p), GRID), BYTE_MUTATIONS),  # arrays: below
    Reader("jsonl", ".jsonl", _build_jsonl, lambda p: read_recorded(str(p), GRID, t_start="metadata")),
    Reader("csv", ".csv", _build_csv, _read_csv),
    Reader("calibration", ".yaml", _build_calibration, _read_calibrated),  # applied to a valid raw scan
]


# ----------------------------------------------------------------------------- mutations
def _lines(fn):
    """A mutation of the file's lines (keeps the trailing newline)."""
    def mutate(data: bytes, rng: np.random.Generator) -> bytes:
        lines = data.split(b"\n")
        return b"\n".join(fn(lines, rng))
    return mutate


def _number(replacement: bytes | Callable[[bytes], bytes]):
    """Replace one random number in the file (text formats) by ``replacement``."""
    def mutate(data: bytes, rng: np.random.Generator) -> bytes:
        spans = [m.span() for m in NUMBER.finditer(data)]
        if not spans:
            return data
        a, b = spans[int(rng.integers(len(spans)))]
        new = replacement(data[a:b]) if callable(replacement) else replacement
        return data[:a] + new + data[b:]
    return mutate


def _missing_key(data: bytes, rng: np.random.Generator) -> bytes:
    """Remove one ``"key": value`` pair from a JSON line, or one field from a CSV line."""
    lines = data.split(b"\n")
    i = int(rng.integers(len(lines)))
    if lines[i].startswith(b"{"):
        obj = json.loads(lines[i])
        if obj:
            obj.pop(list(obj)[int(rng.integers(len(obj)))])
        lines[i] = json.dumps(obj).encode()
    else:
        fields = lines[i].split(b",")
        del fields[int(rng.integers(len(fields)))]
        lines[i] = b",".join(fields)
    return b"\n".join(lines)


def _flip(data: bytes, rng: np.random.Generator) -> bytes:
    out = bytearray(data)
    for i in rng.integers(0, len(out), 8):
        out[i] ^= 1 << int(rng.integers(8))
    return bytes(out)


def _swap_two(lines, rng):
    i, j = rng.integers(1, len(lines), 2)
    lines[i], lines[j] = lines[j], lines[i]
    return lines


MUTATIONS: dict[str, Callable[[bytes, np.random.Generator], bytes]] = {
    "truncated": lambda d, r: d[: int(r.integers(1, len(d)))],
    "byte_flips": _flip,
    "nan": _number(b"NaN"),
    "inf": _number(b"Infinity"),
    "huge": _number(b"1e300"),
    "negative": _number(lambda s: s[1:] if s.startswith(b"-") else b"-" + s),
    "wrong_type": _number(b'"abc"'),
    "missing_key": _missing_key,
    "shuffled_lines": _lines(lambda ls, r: [ls[i] for i in r.permutation(len(ls))]),
    "swapped_lines": _lines(_swap_two),
    "duplicated_line": _lines(lambda ls, r: ls[: (i := int(r.integers(len(ls))))] + [ls[i]] + ls[i:]),
    "empty": lambda d, r: b"",
    "garbage": lambda d, r: bytes(r.integers(0, 256, 2000, dtype=np.uint8)),
}

NPZ_MUTATIONS: dict[str, Callable[[dict, np.random.Generator], dict]] = {
    "nan": lambda a, r: {**a, "profiles": np.where(r.random(a["profiles"].shape) < 0.1, np.nan, a["profiles"])},
    "inf": lambda a, r: {**a, "offsets": np.full_like(a["offsets"], np.inf)},
    "huge": lambda a, r: {**a, "profiles": a["profiles"] * 1e300},
    "negative": lambda a, r: {**a, "profiles": -a["profiles"]},
    "wrong_type": lambda a, r: {**a, "directions": np.array(["x"] * len(a["directions"]))},
    "wrong_shape": lambda a, r: {**a, "profiles": a["profiles"][:, None]},
    "missing_key": lambda a, r: {k: v for k, v in a.items() if k != sorted(a)[int(r.integers(len(a)))]},
    "bad_metadata": lambda a, r: {**a, "metadata": np.array("{not json")},
    "duplicated_rows": lambda a, r: {**a, "directions": np.repeat(a["directions"][:1], len(a["directions"]), 0)},
    "nan_sigma": lambda a, r: {**a, "sigma": np.where(r.random(a["sigma"].shape) < 0.1, np.nan, a["sigma"])},
    "inf_sigma": lambda a, r: {**a, "sigma": np.full_like(a["sigma"], np.inf)},
    "negative_sigma": lambda a, r: {**a, "sigma": -a["sigma"]},
}
#: Mutations that must be refused, and the array the message must name (``None``: any message).
NPZ_REFUSED = {"nan": "profiles", "inf": "offsets", "huge": None, "negative": None, "wrong_type": None,
               "wrong_shape": None, "bad_metadata": None, "nan_sigma": "sigma", "inf_sigma": "sigma",
               "negative_sigma": "sigma"}


def _check(reader: Reader, path: Path) -> str:
    """``"error"`` (the user-error contract holds) or ``"valid"`` (validation accepts the result)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            measurement = reader.read(path)
            validate_measurement(measurement, CSV_GRID if reader.name == "csv" else GRID)
        except (ValueError, FileNotFoundError) as exc:
            message = error_message(exc)
            assert path.name in message, f"{reader.name}: the message does not name the file: {message}"
            return "error"
    return "valid"


@pytest.fixture(scope="module")
def samples(tmp_path_factory) -> dict[str, Path]:
    tmp = tmp_path_factory.mktemp("fuzz")
    return {r.name: r.build(tmp) for r in READERS}


@pytest.mark.parametrize("reader", READERS, ids=lambda r: r.name)
def test_sample_files_are_valid(reader, samples):
    assert _check(reader, samples[reader.name]) == "valid"


CASES = [(r, m) for r in READERS for m in sorted(MUTATIONS) if r.mutations is None or m in r.mutations]


@pytest.mark.parametrize(("reader", "mutation"), CASES, ids=[f"{r.name}-{m}" for r, m in CASES])
def test_byte_and_text_mutations(reader, mutation, samples, tmp_path):
    source = samples[reader.name].read_bytes()
    outcomes = []
    for seed in SEEDS:
        rng = np.random.default_rng([seed, sorted(MUTATIONS).index(mutation)])
        path = tmp_path / f"case{seed}{reader.suffix}"
        path.write_bytes(MUTATIONS[mutation](source, rng))
        outcomes.append(_check(reader, path))
    if mutation in ("empty", "garbage"):
        assert outcomes == ["error"] * len(SEEDS)


@pytest.mark.parametrize("key", ["pivot_mm", "tilt_axis_offset_mm", "tilt_zero_deg", "spin_zero_deg", "step_scale",
                                 "cross_section_mm2", "level_drift_mm_per_s", "sensor_lag_s"])
@pytest.mark.parametrize("value", [1e300, -1e300, 1e-300])
def test_calibration_extreme_values_are_named_errors(key, value, samples, tmp_path):
    """Every geometry value far out of range is refused by the calibration reader itself (an
    extreme value that slipped through once gave a volume of 1.9e-300 mm^3 with exit code 0)."""
    path = tmp_path / "extreme.yaml"
    text = samples["calibration"].read_text()
    path.write_text(re.sub(rf"(?m)^(  {key}: ).*$", rf"\g<1>{value!r}", text))
    assert path.read_text() != text
    if value == 1e-300 and key not in ("step_scale", "cross_section_mm2"):
        assert _check(READERS[-1], path) == "valid"  # a negligible offset, drift or lag is a valid geometry
        return
    with pytest.raises(ValueError, match=rf"{path.name}: rig geometry {key}"):
        READERS[-1].read(path)


@pytest.mark.parametrize("mutation", sorted(NPZ_MUTATIONS))
def test_npz_array_mutations(mutation, samples, tmp_path):
    with np.load(samples["npz"]) as data:
        arrays = {k: data[k] for k in data.files}
    rng = np.random.default_rng(sorted(NPZ_MUTATIONS).index(mutation))
    path = tmp_path / "case.npz"
    np.savez(path, **NPZ_MUTATIONS[mutation](arrays, rng))
    assert "sigma" in arrays  # the sample carries its noise
    outcome = _check(READERS[2], path)
    if mutation in NPZ_REFUSED:
        assert outcome == "error"
    if NPZ_REFUSED.get(mutation):
        with pytest.raises(ValueError, match=rf"case\.npz: measurement array '{NPZ_REFUSED[mutation]}' holds"):
            DipMeasurement.load(path)


def test_missing_file_names_it(tmp_path):
    for reader in READERS:
        path = tmp_path / f"absent{reader.suffix}"
        assert _check(reader, path) == "error"


def test_duplicated_directions_are_reported(samples, tmp_path):
    """Identical directions with different profiles pass, with a warning naming the discrepancy (at least the
    totals' 0.8 against 1.2: the volumes below a height differ most at the top or before)."""
    m = DipMeasurement.load(samples["npz"])
    k = m.n_orientations
    scaled = DipMeasurement(m.directions[:1].repeat(k, 1), m.profiles * torch.linspace(0.8, 1.2, k)[:, None],
                            m.slab_thickness, m.offsets, None, {})
    with pytest.warns(UserWarning, match=r"within 0.5 deg measure different profiles"):
        report = validate_measurement(scaled, GRID)
    assert report.stats["duplicate_direction_pairs"] == k * (k - 1) // 2
    assert 0.4 - 1e-6 <= report.stats["duplicate_max_discrepancy"] <= 1.2


@pytest.mark.parametrize("encoding", ["utf-8-sig", "utf-16-le", "utf-16-be"])
def test_csv_with_a_byte_order_mark_reads_as_the_sample(encoding, samples, tmp_path):
    """Spreadsheet programs write a byte-order mark (and CRLF line ends): the same data, not mojibake."""
    path = tmp_path / "spreadsheet.csv"
    bom = {"utf-8-sig": b"", "utf-16-le": b"\xff\xfe", "utf-16-be": b"\xfe\xff"}[encoding]
    path.write_bytes(bom + samples["csv"].read_text().replace("\n", "\r\n").encode(encoding))
    torch.testing.assert_close(_read_csv(path).profiles, _read_csv(samples["csv"]).profiles)
