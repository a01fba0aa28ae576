"""A leaf's slip or its neighbour's (docs/slippage.md, "Eighth round"): a hand's slip and its forearm's step
the wrist alike, and only the elbow tells them apart; where soft tissue in a new pose mimics the forearm's
step at the elbow as the hand slips, the confirming test named the forearm with full confidence. A slip named
on the forearm is now the hand's where the elbow's residual since the onset sits where it sat in the same pose
before, nearer there than half the forearm's step either way (`SlipMonitor._leaf_or_body`).

The cases are the sweep's (bench_slip_sweep.py --list), replayed through the live loop (`SlipWatch`) in the
service's 1/30 s micro-batches, with the simulator's default soft tissue and slips scheduled in the
performance's own time."""

from __future__ import annotations

import pytest

from flockcal.simulator.performer import Performer
from flockcal.solver.slippage.watch import SlipWatch
from slip_replay import first_slip_event, tree

RATE = 144.0
# Issue 32's promise (README): found within 1 s, named right. No margin: the replay runs on the performance's
# own clock, so load cannot move a detection, and these slips are found 0.16-0.38 s after they land.
WITHIN_S = 1.0


@pytest.mark.parametrize("routine, seed, sensor, at, onset_s, renamed", [
    # Named r_forearm (confidence 1.0) before: the elbow's soft tissue looked like the forearm's step.
    ("exercise", 2, "r_hand", 27.385, 0.05, 1),
    # Named l_forearm before, from an onset 0.22 s after the slip's (soft tissue raised the suspicion there
    # first; the step test's onset is not this check's to move): the onset's tolerance says so.
    ("kiosk", 2, "l_hand", 22.256, 0.25, 1),
    # Named right before and after: a forearm whose elbow stepped stays the forearm, a hand named at once
    # is not looked at again.
    ("kiosk", 3, "l_forearm", 30.5, 0.05, 0),
    ("kiosk", 1, "r_hand", 33.0, 0.05, 0),
])
def test_the_elbow_in_the_same_pose_before_tells_a_hand_from_its_forearm(routine, seed, sensor, at, onset_s, renamed):
    perf = Performer("human", routine=routine, seed=seed, noise="tracker", rate_hz=RATE)
    watch = SlipWatch(tree(perf.model), perf.n_sensors, RATE, perf.names)
    first = first_slip_event(perf, watch, sensor, at, WITHIN_S, onset_s)
    # Tried: without the check the renamed cases name the forearm (docs/slippage.md's table); the counter
    # shows that this check, not another path, named them.
    assert watch.monitor.renamed == renamed, first.to_dict()
    assert first.sensor == sensor, first.to_dict()
    if renamed:
        # The hand's slip re-baselines the wrist alone (named by its child, the hand): the elbow goes on.
        assert first.joints == (sensor,), first.to_dict()
