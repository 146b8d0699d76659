"""The output stages' progress bar (dipnet.outputs.progress) counts to the stages the job runs."""

from __future__ import annotations

import pytest

from dipnet.outputs.progress import STAGES, OutputStages, planned_stages

from progress_bars import RecordingBar


@pytest.mark.parametrize("skipped", [(), ("resolvability", "report")])
def test_output_stages_count_to_the_stages_that_run(monkeypatch, skipped):
    """The bar went from 5/6 to "100% 5/5": its total was every stage, then cut to those that ran."""
    from dipnet.outputs import progress

    RecordingBar.made = []
    monkeypatch.setattr(progress, "tqdm", RecordingBar)
    ran = tuple(s for s in STAGES if s not in skipped)
    stage = OutputStages(stages=ran)
    for name in ran:
        stage(name)
        assert stage.bar.postfix.endswith(name) and stage.bar.total == len(ran)
    stage.close()
    (bar,) = RecordingBar.made
    assert bar.n == bar.total == len(ran)


@pytest.mark.parametrize("output, truth, skipped", [
    ({}, True, {"uncertainty", "report"}),
    ({"resolvability": False, "uncertainty": "linearised", "report": True}, False,
     {"resolvability", "truth and metrics"}),
])
def test_the_planned_stages_leave_out_what_the_options_skip(output, truth, skipped):
    assert planned_stages(output, truth) == tuple(s for s in STAGES if s not in skipped)
