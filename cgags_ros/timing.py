"""Stage timers: every layer reports its stages' wall times (seconds) the same way."""

from __future__ import annotations

import time


class timed:  # noqa: N801 - used like a function: ``with timed(timings, 'stage'):``
    """Add the wall time (s) of a ``with`` block to ``timings[stage]``."""

    def __init__(self, timings: dict[str, float], stage: str) -> None:
        self.timings, self.stage = timings, stage

    def __enter__(self) -> None:
        self.start = time.perf_counter()

    def __exit__(self, *exc) -> None:
        elapsed = time.perf_counter() - self.start
        self.timings[self.stage] = self.timings.get(self.stage, 0.0) + elapsed
