"""One-line user errors: the message behind a failed instantiation, exit codes, missing options."""

import sys

import hydra
import pytest
from hydra.errors import InstantiationException, MissingConfigException
from omegaconf import OmegaConf

from dipnet.core.optional import MissingExtraError
from dipnet.jobs.cli import MissingOptionError, error_message, require_options, run_hydra, user_errors


def _instantiation_error(cause: Exception, message: str = "Error in call to target 'x'") -> InstantiationException:
    """Hydra's error for a target that raised ``cause``."""
    exc = InstantiationException(message)
    exc.__cause__ = cause
    return exc


def test_the_message_is_the_user_error_behind_an_instantiation():
    assert error_message(_instantiation_error(ValueError("resolution must be an integer"))) == \
        "resolution must be an integer"
    assert error_message(KeyError("solver")) == "missing key 'solver'"
    assert error_message(FileNotFoundError(2, "No such file or directory", "/x.npz")) == \
        "/x.npz: No such file or directory"
    assert error_message(ValueError("a\n  b   c")) == "a b c"


def test_a_wrong_type_behind_an_instantiation_names_the_config_node():
    """The audit's case: shape.radius=abc gave Hydra's 'Error in call to target ...: TypeError(...)'."""
    message = error_message(_instantiation_error(TypeError("'>' not supported between instances of 'str' and 'int'"),
                                                 "Error in call to target 'f':\nTypeError(...)\nfull_key: shape"))
    assert message.startswith("shape: an option of the wrong type ('>' not supported")
    assert "check the values given to shape.*" in message


def test_an_option_a_target_refuses_is_named_by_its_path_in_the_config():
    """source.simulator.protocol.clearance_mm=-1 said "protocol clearance_mm must be ...", shape.radius=-1 "shape
    radius must be ...": the option the target names, a keyword it takes, is named by its full path."""
    protocol = "Error in call to target 'dipnet.simulator.physics.DipProtocol':\nValueError(...)\n" \
               "full_key: source.simulator.protocol"
    shape = "Error in call to target 'dipnet.shapes.builtin.builtin_shape':\nValueError(...)\nfull_key: shape"
    assert error_message(_instantiation_error(ValueError("protocol clearance_mm must be >= 0 (mm), got 'abc'"),
                                              protocol)) == \
        "source.simulator.protocol.clearance_mm must be >= 0 (mm), got 'abc'"
    assert error_message(_instantiation_error(ValueError("step_mm must be positive"), protocol)) == \
        "source.simulator.protocol.step_mm must be positive"
    assert error_message(_instantiation_error(ValueError("shape radius must be positive"), shape)) == \
        "shape.radius must be positive"
    # not a keyword of the target, or no target named: the message as it is
    assert error_message(_instantiation_error(ValueError("protocol speed must be positive"), protocol)) == \
        "protocol speed must be positive"
    assert error_message(_instantiation_error(ValueError("radius must be positive"))) == "radius must be positive"


def test_user_errors_exit_2_with_one_line(capsys):
    with pytest.raises(SystemExit) as exit_info, user_errors():
        raise ValueError("bad option")
    assert exit_info.value.code == 2 and capsys.readouterr().err == "error: bad option\n"
    with pytest.raises(RuntimeError), user_errors():  # not a user error: the traceback stays
        raise RuntimeError("a bug")


def test_a_missing_extra_is_one_line_naming_it_and_exit_2(capsys):
    """tune.py without the `sweeps` extra printed a 27-line traceback and exited 1."""
    with pytest.raises(SystemExit) as exit_info, user_errors():
        raise MissingExtraError('tuning needs optuna, which the core install leaves out: pip install "dipnet[sweeps]"')
    assert exit_info.value.code == 2
    assert capsys.readouterr().err == 'error: tuning needs optuna, which the core install leaves out: ' \
                                      'pip install "dipnet[sweeps]"\n'


def test_a_launcher_of_the_sweeps_extra_names_the_extra():
    """hydra/launcher=joblib without the extra gave Hydra's 'Could not find' with no hint of what installs it."""
    exc = MissingConfigException("In 'hydra/config': Could not find 'hydra/launcher/joblib'\nAvailable options in "
                                 "'hydra/launcher':\n\tbasic\nConfig search path:\n\tprovider=hydra")
    assert error_message(exc) == ("In 'hydra/config': Could not find 'hydra/launcher/joblib' Available options in "
                                  "'hydra/launcher': basic (the joblib and submitit launchers come with "
                                  'pip install "dipnet[sweeps]")')


def test_the_error_is_shown_once_and_kept_in_the_log_file(console_and_log_file, capsys):
    """Hydra's console handler repeated every ``error:`` line on stdout; its log file keeps it
    (:func:`dipnet.core.console.report`, tested in tests/core/test_console.py)."""
    console, log_file = console_and_log_file
    with pytest.raises(SystemExit), user_errors():
        raise ValueError("bad option")
    assert console.stream.getvalue() == ""
    assert log_file.read_text() == "error: bad option\n"
    assert capsys.readouterr().err == "error: bad option\n"


def test_every_missing_option_is_named():
    require_options(OmegaConf.create({"a": 1}))
    with pytest.raises(MissingOptionError, match=r"option b, c.d is required: .* e.g. b=\.\.\."):
        require_options(OmegaConf.create({"a": 1, "b": "???", "c": {"d": "???"}}))


@pytest.mark.parametrize("multirun", [False, True])
def test_a_run_directory_hydra_cannot_create_names_the_option(tmp_path, monkeypatch, capsys, multirun):
    """A file where the run (or sweep) directory goes: was "error: /x/afile: File exists" (or "Not a directory"),
    naming no option; Hydra's own mkdir raises it before the job starts."""
    blocker = tmp_path / "afile"
    blocker.write_text("x")
    (tmp_path / "app.yaml").write_text("a: 1\n")

    @hydra.main(version_base=None, config_path=str(tmp_path), config_name="app")
    def app(cfg) -> int:
        return 0

    option = "hydra.sweep.dir" if multirun else "hydra.run.dir"
    monkeypatch.setenv("HYDRA_FULL_ERROR", "1")
    monkeypatch.setattr(sys, "argv", ["app", *(["-m"] if multirun else []), f"{option}={blocker}/sub"])
    with pytest.raises(SystemExit) as exit_info:
        run_hydra(app)
    err = capsys.readouterr().err
    assert exit_info.value.code == 2
    kind = "sweep" if multirun else "run"
    assert f"error: cannot create the {kind} directory {blocker}/sub ({blocker} is a file, not a folder)" in err
    assert f"with {option}=..." in err
    assert "File exists" not in err and "Not a directory" not in err
