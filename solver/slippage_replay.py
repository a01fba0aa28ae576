"""The live slippage loop in one object, as the server runs it: frames → segmented accumulator → joint
fits → `SlipMonitor` → new segments. Used to replay recorded takes and by the tests and benchmark.
"""

from __future__ import annotations

import numpy as np

from flockcal.solver.fits import PairFits
from flockcal.solver.segments import SegmentedAccumulator
from flockcal.solver.slippage import SlipMonitor


class SlipReplay:
    """Feed frames in live-sized batches (`batch_s`); after each batch the tree joints are re-fitted
    (on their post-slip segment where a slip was found) and the monitor sees the new estimates."""

    def __init__(self, joints, n_sensors: int, rate_hz: float, names=None, batch_s: float = 1 / 30,
                 **monitor_options):
        self.joints = np.asarray(joints, dtype=int).reshape(-1, 2)
        self.segments = SegmentedAccumulator(n_sensors)
        self.monitor = SlipMonitor(self.joints, n_sensors, rate_hz, names, **monitor_options)
        self.step = max(1, int(round(batch_s * rate_hz)))
        self.fits: PairFits | None = None

    @property
    def events(self) -> list:
        return self.monitor.events

    def feed(self, times, rotations, positions, valid=None) -> list:
        """Add frames; returns the events found in them."""
        ts = np.asarray(times, dtype=float)
        out = []
        for a in range(0, len(ts), self.step):
            sl = slice(a, a + self.step)
            v = None if valid is None else valid[sl]
            self.segments.update(ts[sl], rotations[sl], positions[sl], v)
            self.fits = self.segments.pair_fits(self.joints)
            found = self.monitor.update(ts[sl], rotations[sl], positions[sl], v, self.fits.c, self.fits.l)
            if found:
                self.segments.apply(found)
                out += found
        return out
