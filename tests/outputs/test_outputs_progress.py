"""The output stages' progress bar (dipnet.outputs.progress) ends full whatever was skipped."""

from __future__ import annotations

import pytest

from dipnet.outputs.progress import STAGES, OutputStages

from progress_bars import RecordingBar


@pytest.mark.parametrize("skipped", [(), ("resolvability", "report")])
def test_output_stages_end_full_whatever_was_skipped(monkeypatch, skipped):
    from dipnet.outputs import progress

    RecordingBar.made = []
    monkeypatch.setattr(progress, "tqdm", RecordingBar)
    stage = OutputStages()
    ran = [s for s in STAGES if s not in skipped]
    for name in ran:
        stage(name)
        assert stage.bar.postfix.endswith(name)
    stage.close()
    (bar,) = RecordingBar.made
    assert bar.n == bar.total == len(ran)
