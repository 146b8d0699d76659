"""Progress bars end where the work ended (dipnet.solvers.progress): a plateau stop leaves no bar stalled short of its
total."""

from __future__ import annotations

import torch

from dipnet.solvers import optimize
from dipnet.solvers.optimize import DataTerm, optimise
from dipnet.solvers.progress import stop_bar

from progress_bars import RecordingBar
from solver_helpers import noise_free_problem, one_thread  # noqa: F401 (one_thread: autouse fixture)


def test_a_plateau_stop_ends_the_bar_at_the_steps_run(monkeypatch):
    RecordingBar.made = []
    monkeypatch.setattr(optimize, "tqdm", RecordingBar)
    _, op, meas = noise_free_problem(2, lambda p: (p**2).sum(dim=-1) < 400.0)
    z = torch.zeros(1, requires_grad=True)
    fixed = torch.full(op.grid.shape, 0.5)                     # the loss cannot move: a plateau after 2 windows
    hist = optimise([z], lambda: fixed + 0 * z, DataTerm(op, meas.profiles), [], iterations=500, lr=0.1,
                    tol=1e-3, window=20, desc="test")
    (bar,) = RecordingBar.made
    ran = len(hist["loss"])
    assert ran == 40 < 500
    assert bar.n == ran and bar.total == ran                   # full, not 40 of 500
    assert "plateau at step 40" in bar.postfix


def test_a_bar_that_ran_to_its_total_is_left_as_it_is():
    with RecordingBar(total=5) as bar:
        bar.update(5)
        stop_bar(bar, "converged")
    assert bar.n == bar.total == 5 and not bar.postfix
