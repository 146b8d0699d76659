"""Run an entry-point script (``python scripts/<name>.py <argv>``) in this process, for the tests.

A subprocess pays ~5-7 s of importing torch before the first line of the script runs; a test that only
checks what the script prints and its exit code gets the same from the script's ``@hydra.main`` function
called here as its ``__main__`` block calls it: ``sys.exit(run_hydra(main))`` with ``sys.argv`` set, Hydra's
errors re-raised (``HYDRA_FULL_ERROR``), stdout and stderr read with ``capsys``. Each entry point keeps at
least one real-subprocess test (the process's own exit code).

What a job changes in the process is put back afterwards, so the next test sees what it would after a
subprocess: the root logger's handlers and level (Hydra's job logging replaces them), the log-record factory
and ``warnings.showwarning`` (:func:`~dipnet.jobs.warnings_once.log_warnings_once`, installed afresh for
every run as in a new process), Hydra's run config (:class:`HydraConfig`), torch's thread count and the
random generators the job seeds.
"""

from __future__ import annotations

import logging
import random
import subprocess
import sys
import warnings

import numpy as np
import pytest
import torch
from hydra.core.hydra_config import HydraConfig

from dipnet.jobs import warnings_once
from dipnet.jobs.cli import run_hydra
from script_modules import SCRIPTS, load_script


def run_script(name: str, *argv: str, monkeypatch: pytest.MonkeyPatch,
               capsys: pytest.CaptureFixture[str] | None) -> subprocess.CompletedProcess:
    """``python scripts/<name>.py *argv`` in this process: its exit code and what it printed (``capsys``
    ``None``, as in a module-scoped fixture: its exit code, and ``""`` for the output)."""
    script = load_script(name)
    path = str(SCRIPTS / f"{name}.py")
    root = logging.getLogger()
    handlers, level = root.handlers[:], root.level
    factory, hydra_cfg, threads = logging.getLogRecordFactory(), HydraConfig.instance().cfg, torch.get_num_threads()
    rng = torch.get_rng_state(), np.random.get_state(), random.getstate()
    monkeypatch.setattr(sys, "argv", [path, *argv])
    monkeypatch.setenv("HYDRA_FULL_ERROR", "1")
    monkeypatch.setenv("MPLBACKEND", "Agg")
    monkeypatch.setattr(warnings, "showwarning", warnings.showwarning)
    monkeypatch.setattr(warnings_once, "_installed", False)
    if capsys is not None:
        capsys.readouterr()  # what the test printed before is not the script's
    try:
        try:
            sys.exit(run_hydra(script.main))
        except SystemExit as exc:
            code = exc.code
        returncode = 0 if code is None else code if isinstance(code, int) else 1
        if not isinstance(code, int | None):  # sys.exit("text") prints the text, exit code 1
            print(code, file=sys.stderr)
        out, err = capsys.readouterr() if capsys is not None else ("", "")
    finally:
        for handler in root.handlers:
            if handler not in handlers:
                handler.close()
        root.handlers[:] = handlers
        root.setLevel(level)
        logging.setLogRecordFactory(factory)
        HydraConfig.instance().cfg = hydra_cfg
        torch.set_num_threads(threads)
        torch.set_rng_state(rng[0])
        np.random.set_state(rng[1])
        random.setstate(rng[2])
    return subprocess.CompletedProcess([sys.executable, path, *argv], returncode, out, err)


def one_line_error(proc: subprocess.CompletedProcess, code: int = 2, prefix: str = "error: ") -> str:
    """The one line a script printed on stderr for a user error (exit ``code``), once on the terminal: not
    repeated on stdout by Hydra's console log."""
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert proc.returncode == code and len(lines) == 1 and lines[0].startswith(prefix), proc.stderr[-3000:]
    assert lines[0] not in proc.stdout, proc.stdout[-3000:]
    return lines[0]


@pytest.fixture
def script_run(monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]):
    """``run(name, run_dir, *overrides)``: ``python scripts/<name>.py hydra.run.dir=<run_dir> *overrides`` in
    this process (:func:`run_script`), bound to the test's ``monkeypatch`` and ``capsys``."""
    def run(name: str, run_dir, *overrides: str) -> subprocess.CompletedProcess:
        return run_script(name, f"hydra.run.dir={run_dir}", *overrides, monkeypatch=monkeypatch, capsys=capsys)
    return run
