"""Feedback while a job writes its outputs: one progress bar over the named stages after the solve."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from tqdm.auto import tqdm

#: The stages a reconstruction job runs after its solve, in order (:func:`planned_stages`: those of one job).
STAGES = ("consistency", "resolvability", "truth and metrics", "uncertainty", "meshes and figures", "report")


def planned_stages(output: Mapping[str, Any], truth: bool) -> tuple[str, ...]:
    """The stages of :data:`STAGES` a job runs with these ``output`` options (``truth``: its shape is known)."""
    runs = {"resolvability": output.get("resolvability", True), "truth and metrics": truth,
            "uncertainty": output.get("uncertainty"), "report": output.get("report")}
    return tuple(s for s in STAGES if runs.get(s, True))


class OutputStages:
    """A bar that names the stage running: ``stage = OutputStages(); stage("figures"); ...; stage.close()``.

    Each call marks the previous stage done and shows the new one's name; the total is the number of
    ``stages`` the job runs (:func:`planned_stages`), so the bar counts to it and ends full.
    """

    def __init__(self, enabled: bool = True, stages: tuple[str, ...] = STAGES) -> None:
        self.bar = tqdm(total=len(stages), desc="outputs", unit="stage", disable=not enabled, leave=False)
        self.started = 0

    def __call__(self, name: str) -> None:
        if self.started:
            self.bar.update()
        self.started += 1
        self.bar.set_postfix_str(name)

    def close(self) -> None:
        """Count the last stage done and close the bar."""
        if self.started:
            self.bar.update()
        self.bar.close()
