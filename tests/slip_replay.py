"""What the slip tests feed the live loop: a body's tree as (child, parent) joints, a simulated
performer's frames over a span of its own clock, at its own rate, and one slip replayed through it."""

from __future__ import annotations

import numpy as np

from slip_scoring import attributes_slip_to


def tree(model) -> np.ndarray:
    """(p, 2) (child, parent) sensor indices of the model's true tree."""
    return np.array([[i, int(p)] for i, p in enumerate(model.parent) if p >= 0])


def frames(perf, t0: float, t1: float):
    """(times, R, t, valid) of the performer's samples in [t0, t1) seconds, at its rate."""
    rate = perf.rate_hz
    times = np.arange(int(round(t0 * rate)), int(round(t1 * rate))) / rate
    return (times, *perf.poses(times))


def first_slip_event(perf, watch, sensor: str, at: float, within_s: float, onset_s: float):
    """Feed `watch` (a live loop on `perf`) the performance from 0 to `at` with nothing slipped (no event
    allowed), slip `sensor` 2 cm at `at` (the performer's own clock) and feed `within_s` more: the first
    event, which must name `sensor`, within `within_s`, at an onset within `onset_s` of `at`."""
    assert watch.feed(*frames(perf, 0.0, at)) == [], "a false alarm before the slip"
    perf.inject_slip(sensor, 0.02, at_time=at)
    found = watch.feed(*frames(perf, at, at + within_s))
    assert found, f"the {sensor} slip at {at} s was not found within {within_s} s"
    first = found[0]
    assert attributes_slip_to(first, sensor, perf.model.names, perf.model.parent), first.to_dict()
    assert first.detected_s - at <= within_s and abs(first.time_s - at) <= onset_s, first.to_dict()
    return first
