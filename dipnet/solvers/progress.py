"""Progress bars of the iterative solvers that end where the solve ended."""

from __future__ import annotations

from tqdm.auto import tqdm


def stop_bar(bar: tqdm, reason: str) -> None:
    """End ``bar`` at the steps that ran (a solve that stopped early: plateau, converged) and
    say why in its postfix, so it neither stalls short of its total nor promises more time."""
    if bar.n < (bar.total or 0):
        bar.total = bar.n
        bar.set_postfix_str(reason, refresh=False)
    bar.refresh()
