"""Feedback while a job writes its outputs: one progress bar over the named stages after the solve."""

from __future__ import annotations

from tqdm.auto import tqdm

#: The stages a reconstruction job runs after its solve (the bar's total; skipped ones are left out at the end).
STAGES = ("consistency", "resolvability", "truth and metrics", "uncertainty", "meshes and figures", "report")


class OutputStages:
    """A bar that names the stage running: ``stage = OutputStages(); stage("figures"); ...; stage.close()``.

    Each call marks the previous stage done and shows the new one's name; :meth:`close` sets
    the total to the stages that ran, so the bar ends full whatever was skipped.
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
        """Count the last stage done, end the bar at the stages that ran, and close it."""
        if self.started:
            self.bar.update()
        self.bar.total = self.started
        self.bar.refresh()
        self.bar.close()
