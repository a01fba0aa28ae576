"""Clocks for the fake tracker: a manual one tests drive by hand, and the wall clock (monotonic).
"""

from __future__ import annotations

import time


class ManualClock:
    """A clock tests drive by hand: `advance(dt)` moves simulated time on."""

    def __init__(self, t: float = 0.0) -> None:
        self.t = float(t)

    def __call__(self) -> float:
        return self.t

    def advance(self, dt: float) -> float:
        self.t += float(dt)
        return self.t


class WallClock:
    """Seconds of wall time since construction (monotonic)."""

    def __init__(self) -> None:
        self._t0 = time.monotonic()

    def __call__(self) -> float:
        return time.monotonic() - self._t0
