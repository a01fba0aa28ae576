"""What the slip tests feed the live loop: a body's tree as (child, parent) joints, and a simulated
performer's frames over a span of its own clock, at its own rate."""

from __future__ import annotations

import numpy as np


def tree(model) -> np.ndarray:
    """(p, 2) (child, parent) sensor indices of the model's true tree."""
    return np.array([[i, int(p)] for i, p in enumerate(model.parent) if p >= 0])


def frames(perf, t0: float, t1: float):
    """(times, R, t, valid) of the performer's samples in [t0, t1) seconds, at its rate."""
    rate = perf.rate_hz
    times = np.arange(int(round(t0 * rate)), int(round(t1 * rate))) / rate
    return (times, *perf.poses(times))
