"""One hour of clean simulated walking at tracker noise, with the simulator's default 12 mm soft tissue,
through the live loop: no slip reported (docs/slippage.md "Measured (benchmarks/bench_slippage.py)": 0 in an
hour each of STA exercise, walk and kiosk).
Slow (about 4 minutes on one core): run with `python -m pytest -m slow tests/test_slippage_soak.py`."""

from __future__ import annotations

import numpy as np
import pytest

from flockcal.simulator.performer import Performer
from flockcal.solver.slippage.watch import SlipWatch

RATE = 100.0


@pytest.mark.slow
def test_one_hour_of_clean_walk_raises_no_false_alarm():
    seconds = 3600.0
    perf = Performer("human", routine="walk", seed=12, noise="tracker", rate_hz=RATE, seconds=seconds, period=seconds)
    joints = np.array([[i, int(p)] for i, p in enumerate(perf.model.parent) if p >= 0])
    replay = SlipWatch(joints, perf.n_sensors, RATE, perf.names)
    for t0 in np.arange(0.0, seconds, 60.0):
        times = np.arange(int(round(t0 * RATE)), int(round((t0 + 60.0) * RATE))) / RATE
        replay.feed(times, *perf.poses(times))
    assert replay.events == []
    assert replay.monitor.ready.all()
