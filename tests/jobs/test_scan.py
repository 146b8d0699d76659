"""The scan job's plan settings: one rig geometry (values or a calibration file), the deepest lowering."""

import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_module

from dipnet.core.calibration_file import TANK_CONFIG_KEY, Calibration, CalibrationFileError, save_calibration
from dipnet.core.geometry import RigGeometry
from dipnet.core.grid import Grid
from dipnet.core.rawscan import read_rawscan
from dipnet.jobs.options import ConfigError
from dipnet.jobs.deprecations import upgrade_scan_config
from dipnet.jobs.scan import deepest_lowering, orientations_from_config, plan_settings, scan_geometry

from rig_helpers import make_world
from script_runs import one_line_error


def _scan_cfg(*overrides):
    with initialize_config_module(config_module="dipnet.conf", version_base="1.3"):
        return upgrade_scan_config(compose(config_name="scan", overrides=list(overrides)))


def test_the_rig_geometry_node_is_the_plans_geometry():
    cfg = _scan_cfg("rig=grbl", "rig.geometry.pivot_mm=12", "rig.origin_height_mm=40")
    settings = plan_settings(cfg)
    assert settings["geometry"] == RigGeometry(pivot_mm=12.0) and settings["origin_height_mm"] == 40
    assert settings["step_mm"] == cfg.protocol.step_mm and settings["max_lower_mm"] is None


def test_a_calibration_file_gives_the_geometry_but_not_beside_values(tmp_path):
    path = save_calibration(Calibration(RigGeometry(pivot_mm=7.0), rig="grbl-rig", tank="t"), tmp_path / "c.yaml")
    assert scan_geometry(_scan_cfg("rig=grbl", f"+rig.calibration={path}").rig) == RigGeometry(pivot_mm=7.0)
    with pytest.raises(ValueError, match="either as a calibration file .* or as values"):
        scan_geometry(_scan_cfg("rig=grbl", f"+rig.calibration={path}", "rig.geometry.pivot_mm=3").rig)


def test_the_deepest_lowering_is_the_configured_one():
    assert deepest_lowering(_scan_cfg("rig=grbl", "rig.max_lower_mm=80")) == {"max_lower_mm": 80.0,
                                                                                "max_lower_source": "rig.max_lower_mm"}


def test_a_fibonacci_plan_beyond_max_tilt_spreads_every_dip_within_it(caplog):
    """Before: n_dips=8 max_tilt_deg=40 dropped 6 of the 8 directions without a word and scanned 2. Now all 8
    are spread over tilts 0-40 deg (as reconstruct.py keeps its plan within the reach), and a log line says so."""
    with caplog.at_level("INFO", logger="dipnet.rig.runner"):
        pairs = orientations_from_config(_scan_cfg("n_dips=8", "max_tilt_deg=40"))
    tilts = [tilt for tilt, _ in pairs]
    assert len(set(pairs)) == 8 and max(tilts) <= 40.0 and max(tilts) > 35.0 and tilts == sorted(tilts)
    assert "6 of the n_dips=8 fibonacci directions tilt beyond max_tilt_deg=40: all 8 spread over tilts 0-40 deg" \
        in caplog.text
    # within the limit the plan is the hemisphere's Fibonacci set, unchanged
    assert orientations_from_config(_scan_cfg("n_dips=8", "max_tilt_deg=90")) == \
        orientations_from_config(_scan_cfg("n_dips=8", "max_tilt_deg=120"))
    assert len(orientations_from_config(_scan_cfg("n_dips=8", "max_tilt_deg=10"))) == 8  # before: "no orientation left"


@pytest.mark.parametrize("overrides,message", [
    (["orientations=random", "n_dips=8", "max_tilt_deg=40"],
     r"orientations=random puts \d of its n_dips=8 directions beyond max_tilt_deg=40: use orientations=fibonacci"),
    (["n_dips=8", "max_tilt_deg=0"], r"max_tilt_deg=0 leaves no tilt to spread n_dips=8 fibonacci directions over"),
    (["n_dips=8", "max_tilt_deg=-5"], r"max_tilt_deg=-5 leaves no tilt"),
])
def test_a_set_the_tilt_limit_cannot_hold_is_refused_by_name(overrides, message):
    with pytest.raises(ValueError, match=message):
        orientations_from_config(_scan_cfg(*overrides))


def test_scan_config_runs_through_hydra(tmp_path):
    from hydra import compose, initialize_config_module

    from dipnet.jobs.scan import scan_from_config

    overrides = ["rig=fake_marlin", "sensor=sics", "n_dips=2", "protocol.step_mm=10", "fsync=false",
                 "progress=false", "rig.fake.shape.radius=30"]
    with initialize_config_module(config_module="dipnet.conf", version_base="1.3"):
        cfg = compose(config_name="scan", overrides=overrides)
    raw = scan_from_config(cfg, tmp_path / "rawscan.jsonl")
    assert len(raw.completed()) == 2
    stored = read_rawscan(tmp_path / "rawscan.jsonl")
    assert stored.header.quantity == "mass_g" and stored.header.rig == "fake-marlin"
    assert stored.orientations[0].meta["t_start_mm"] == -cfg.rig.origin_height_mm
    assert stored.header.config["scan"]["sensor"]["device"]["style"] == "sics"


def test_the_scans_tank_is_recorded_and_another_tanks_calibration_refused(tmp_path):
    """``+rig.tank`` was kept only in the scan config, so a reader took another tank's calibration file
    silently. The header records it (``tank_id``), and the reader refuses that file naming both tanks."""
    from dipnet.jobs.scan import scan_from_config
    from dipnet.preprocessing.recorded import read_raw_recording

    cfg = _scan_cfg("rig=fake_marlin", "n_dips=2", "protocol.step_mm=10", "fsync=false", "progress=false",
                    "rig.fake.shape.radius=30", "+rig.tank=other-tank")
    scan_from_config(cfg, tmp_path / "rawscan.jsonl")
    raw = read_rawscan(tmp_path / "rawscan.jsonl")
    assert raw.header.config[TANK_CONFIG_KEY] == "other-tank"
    path = save_calibration(Calibration(RigGeometry(), rig=raw.header.rig, tank="lab-tank-1"), tmp_path / "c.yaml")
    with pytest.raises(CalibrationFileError, match="calibrated on tank 'lab-tank-1', not on 'other-tank'"):
        read_raw_recording(tmp_path / "rawscan.jsonl", Grid(8, extent=100.0), calibration=path)


def test_stock_3axis_preset_works_out_of_the_box(meshes_dir, tmp_path):
    from hydra import compose, initialize_config_module

    from dipnet.jobs.scan import scan_from_config

    overrides = ["rig=grbl_3axis", "rig.controller.url=fakerig://stock3/grbl", "rig.sensor_url=fakerig://stock3/level",
                 "rig.controller.timeout=0.3", "n_dips=3", "protocol.step_mm=20", "fsync=false",
                 "progress=false"]
    with initialize_config_module(config_module="dipnet.conf", version_base="1.3"):
        cfg = compose(config_name="scan", overrides=overrides)
    # a factory-set 3-axis board: no homing ($22=0), no soft limits, MPos in reports
    world = make_world(meshes_dir, "stock3", status_axes="XYZ", axes=dict(cfg.rig.controller.axes),
                       grbl_settings={22: 0})
    assert not world.alarm
    raw = scan_from_config(cfg, tmp_path / "rawscan.jsonl")
    assert len(raw.completed()) == 3 and world.position().lower_mm == 0.0
    assert raw.header.config["controller"]["status_axes"] == "XYZ"


# ----------------------------------------------------------------------------- scripts/scan.py: bad options
SCAN_SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "scan.py"
QUICK_SCAN = ("n_dips=2", "protocol.step_mm=20", "fsync=false", "progress=false")


def _scan_script(run_dir: Path, *overrides: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCAN_SCRIPT), f"hydra.run.dir={run_dir}", *overrides],
                          capture_output=True, text=True, timeout=300)


def _error_line(done: subprocess.CompletedProcess, code: int = 2) -> str:
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    assert done.returncode == code and lines and lines[-1].startswith("error: "), done.stderr[-2000:]
    return lines[-1]


@pytest.mark.parametrize("overrides,message", [
    # +n_dip=4 (before: it ran the full 40-dip default scan, exit 0): the real process, in the test below
    # before: the 400 deg tilt was dropped without a word and one orientation scanned
    (["orientations=grid", "tilts=[0,400]", "spins=[0]"],
     "error: tilts=[0,400]: 400 deg outside the rig's tilt range [0, 90] deg (max_tilt_deg)"),
    (["orientations=grid", "tilts=[0,50]", "spins=[0]", "max_tilt_deg=45"],
     "error: tilts=[0,50]: 50 deg outside the rig's tilt range [0, 45] deg (max_tilt_deg)"),
    # before: the tilts were ignored and the 40-dip Fibonacci scan ran
    (["tilts=[0,30]", "spins=[0]"],
     "error: tilts and spins set a grid plan, but orientations=fibonacci: add orientations=grid, or drop them"),
    # before: a string is true to Python: home=no homed the rig, confirm_position=off accepted an unhomed position
    # after an alarm, fsync=no synced every line, all exit 0 without a word
    (["home=no"], "error: home must be true or false or null, got 'no'; nothing moved"),
    (["confirm_position=off"], "error: confirm_position must be true or false, got 'off'; nothing moved"),
    (["fsync=no"], "error: fsync must be true or false, got 'no'; nothing moved"),
    # before: n_dips=1.5 scanned 1 dip and seed=1.5 used seed 1, exit 0; seed=abc "invalid literal for int() with base
    # 10: 'abc'"; metadata=5 "TypeError: 'int' object is not iterable" (a traceback); max_tilt_deg=true spread the
    # dips over 1 deg
    (["n_dips=1.5"], "error: n_dips must be a whole number, got 1.5 (2.5 is not cut to 2)"),
    (["seed=1.5"], "error: seed must be a whole number, got 1.5 (2.5 is not cut to 2)"),
    (["seed=abc"], "error: seed must be a whole number, got 'abc'"),
    (["metadata=5"], "error: metadata must be a mapping of free-form notes (e.g. '+metadata={object: cat}') or "
                     "empty, got 5; nothing moved"),
    (["max_tilt_deg=true"], "error: max_tilt_deg must be a number of degrees (the rig's tilt limit, e.g. 90), got "
                            "True; nothing moved"),
    # before: name=../x wrote the scan outside scans/ (scans/../x), name= into scans/ itself, exit 0
    (["name=../x"], "error: name must be a plain folder name, the scan's folder scans/<name> (no '/' or '..'), got "
                    "'../x'; nothing moved (to write elsewhere, set hydra.run.dir)"),
    (["name="], "error: name must be a plain folder name, the scan's folder scans/<name> (no '/' or '..'), got "
                "''; nothing moved (to write elsewhere, set hydra.run.dir)"),
    (["monitor=true", "monitor_port=abc"],
     "error: monitor_port must be a whole number, got 'abc'"),
])
def test_scan_script_refuses_bad_options_before_anything_moves(tmp_path, script_run, overrides, message):
    assert _error_line(script_run("scan", tmp_path, *QUICK_SCAN, *overrides)) == message
    assert not (tmp_path / "rawscan.jsonl").exists()


def test_an_adaptive_scan_refuses_a_percentage_for_its_stopping_fraction(tmp_path, script_run):
    """Before: planner.stop_uncertainty=5 (meant as 5 %) stopped the scan after its 4 initial dips of a budget of 8,
    exit 0, "scan complete" (the expected error fraction is below 5 from the first step)."""
    done = script_run("scan", tmp_path, "+planner=adaptive", "planner.budget=8", "planner.initial_dips=4",
                      "planner.stop_uncertainty=5", "protocol.step_mm=20", "fsync=false", "progress=false")
    assert _error_line(done) == (
        "error: stop_uncertainty must be a fraction in (0, 1) or null (the share of the object's volume expected "
        "misclassified, e.g. 0.05), got 5 (5 would stop after the first 4 dips, whatever the budget; "
        "for 5 % give 0.05)")
    assert not (tmp_path / "rawscan.jsonl").exists()


def test_scan_script_process_refuses_an_unknown_option_with_exit_2(tmp_path):
    """The cases above run the script in this process; here the process itself (its exit code 2), on an option no
    code reads (before: +n_dip=4 ran the full 40-dip default scan, exit 0)."""
    assert _error_line(_scan_script(tmp_path, *QUICK_SCAN, "+n_dip=4")) == \
        "error: unknown option n_dip: no code reads it; did you mean n_dips?"
    assert not (tmp_path / "rawscan.jsonl").exists()


def test_scan_script_options_the_scan_reads_without_a_default_are_accepted():
    """``+rig.tank``, ``+rig.calibration`` and ``+metadata.*`` are added keys the scan reads
    (docs/guide/real-data.md)."""
    from script_modules import load_script

    added = load_script("scan")._adds_a_read_key
    assert added("+rig.tank=lab-tank-1") and added("+rig.calibration=c.yaml") and added("+metadata.operator=bob")
    assert not added("+n_dip=4") and not added("+rig.tanks=x") and not added("+metadatas=1")


@pytest.mark.slow
def test_scan_script_refuses_to_resume_with_other_dip_settings(tmp_path):
    """Before: a resume with another stop, origin height or pivot appended its dips to the recorded ones."""
    grid = ("orientations=grid", "spins=[0]")
    first = _scan_script(tmp_path, *QUICK_SCAN, *grid, "tilts=[0]")
    assert first.returncode == 0, first.stderr[-2000:]
    line = _error_line(_scan_script(tmp_path, *QUICK_SCAN, *grid, "tilts=[0,30]", "protocol.stop_mm=60",
                                    "rig.origin_height_mm=40", "rig.geometry.pivot_mm=5"))
    assert "cannot resume" in line and "protocol.stop_mm (config.plan.stop_mm) 110.0 -> 60" in line
    assert "rig.origin_height_mm (config.plan.origin_height_mm) 50.0 -> 40" in line
    assert "rig.geometry.pivot_mm (config.rig_geometry.pivot_mm) 0.0 -> 5.0" in line
    assert len(read_rawscan(tmp_path / "rawscan.jsonl").completed()) == 1  # nothing appended
    again = _scan_script(tmp_path, *QUICK_SCAN, *grid, "tilts=[0,30]")  # the recorded settings: resumes
    assert again.returncode == 0 and len(read_rawscan(tmp_path / "rawscan.jsonl").completed()) == 2


@pytest.mark.slow
def test_scan_script_stops_on_a_sensor_sending_error_lines(tmp_path):
    """Before: the default pattern read 'ERR 42' as a stable 42 mm."""
    line = _error_line(_scan_script(tmp_path, *QUICK_SCAN, "+rig.fake.sensor_format={level_format: 'ERR 42'}"),
                       code=3)
    assert "no reading in 5 line(s); the last: not a level reading: 'ERR 42'" in line and "object lifted" in line


def test_scan_refuses_a_safe_position_below_the_start(tmp_path, script_run):
    done = script_run("scan", tmp_path, *QUICK_SCAN, "protocol.safe_mm=200")
    assert one_line_error(done) == ("error: protocol.safe_mm=200 must be <= protocol.start_mm=0: lowering positions "
                                    "grow downward (mm), and the safe position, where the object turns, must be no "
                                    "deeper than the first reading's; nothing moved")


ADAPTIVE_QUICK = ("+planner=adaptive", "planner.budget=5", "planner.batch_size=2", "planner.initial_dips=3",
                  "+planner.resolution=16", "planner.planner.resolution=16", "protocol.step_mm=10", "fsync=false",
                  "progress=false", "rig.fake.shape.radius=30")


def test_an_adaptive_scan_keeps_within_the_rigs_tilt_limit(tmp_path):
    """The audit's case: ``max_tilt_deg=35 +planner=adaptive`` planned over the whole hemisphere and dipped at tilts
    60, 80, 90 and 70 deg, beyond the rig's mechanical limit, no word. Now the default reach ends at max_tilt_deg and
    a reach beyond it is refused before anything moves."""
    from dipnet.core.orientations import direction_to_rig
    from dipnet.jobs.scan import scan_job

    raw = scan_job(_scan_cfg("max_tilt_deg=35", *ADAPTIVE_QUICK), tmp_path / "rawscan.jsonl")
    tilt, _ = direction_to_rig(raw.directions())
    assert len(raw.completed()) == 5 and tilt.max() <= 35 + 1e-6
    with pytest.raises(ConfigError, match=r"reach.tilt_range_deg=\[0.0, 90.0\] plans tilts beyond max_tilt_deg=35 "
                                         r"\(the rig's mechanical limit\): give reach.tilt_range_deg=\[0,35\]"):
        scan_job(_scan_cfg("max_tilt_deg=35", "+reach=hemisphere", *ADAPTIVE_QUICK), tmp_path / "other.jsonl")
    assert not (tmp_path / "other.jsonl").exists()


def test_an_adaptive_scan_replayed_whole_with_another_rig_geometry_is_refused(tmp_path):
    """The audit's case: ``scripts/scan.py +planner=adaptive`` run again on a file that holds every dip of its plan
    replayed it with exit 0 although the recording was made with another rig geometry (a wrong result, silently):
    the header was compared only when a runner ran for new dips. Now the replay is refused with the resume's message
    before any dip is read back, and replays with the recorded settings."""
    from dipnet.core.rawscan import RawScanFileError
    from dipnet.jobs.scan import scan_job

    path = tmp_path / "rawscan.jsonl"
    assert len(scan_job(_scan_cfg(*ADAPTIVE_QUICK), path).completed()) == 5
    recorded = path.read_bytes()
    with pytest.raises(RawScanFileError, match=r"cannot resume, the new scan differs from the recorded one in "
                                               r"rig.geometry.pivot_mm \(config.rig_geometry.pivot_mm\) 0.0 -> 5.0"):
        scan_job(_scan_cfg("rig.geometry.pivot_mm=5", *ADAPTIVE_QUICK), path)
    assert path.read_bytes() == recorded
    assert len(scan_job(_scan_cfg(*ADAPTIVE_QUICK), path).completed()) == 5 and path.read_bytes() == recorded


@pytest.mark.parametrize("option", ["rig.controller.url", "rig.sensor_url"])
def test_an_empty_port_url_is_refused_naming_its_option(tmp_path, option):
    """``scan.py rig.controller.url=''`` stopped as a rig fault, exit 3: "scan stopped at connecting: RigDisconnected:
    cannot open : [Errno 2] could not open port : ...", naming no option; now refused before connecting."""
    from dipnet.jobs.scan import scan_from_config

    cfg = _scan_cfg(f"{option}=''", "n_dips=2", "protocol.step_mm=10", "fsync=false", "progress=false")
    with pytest.raises(ConfigError, match=rf"{option} is empty \(''\): give the port's pyserial URL .*nothing moved"):
        scan_from_config(cfg, tmp_path / "rawscan.jsonl")
    assert not (tmp_path / "rawscan.jsonl").exists()
