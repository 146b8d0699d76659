"""A tqdm that records its bars, for the tests of progress bars (tests/solvers, tests/outputs)."""

from __future__ import annotations

import io

from tqdm.auto import tqdm


class RecordingBar(tqdm):
    """A tqdm that keeps every instance, to read its final count and total after it closed."""

    made: list["RecordingBar"] = []

    def __init__(self, *args, **kwargs):
        kwargs["disable"] = False
        kwargs["file"] = io.StringIO()
        super().__init__(*args, **kwargs)
        RecordingBar.made.append(self)
