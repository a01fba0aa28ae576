"""The frame-rate step test (docs/slippage.md, "Fourth round"): a slip that lands as the limbs start a sweep
they have not made before, where the confirming test's pose model extrapolates and refutes it, is found
from the frames around it alone (a step shared by every joint of the sensor, in its own frame, against a
cubic in time and the joint's own rotation), and a fresh kiosk guest's fast hands raise no alarm with it.

The cases are the kiosk routine, seed 1, with the simulator's default soft tissue, fed through the live
loop (`SlipWatch`) in the service's 1/30 s micro-batches; slips are scheduled in the performance's own
time (the simulator's clock), so load cannot move them."""

from __future__ import annotations

import copy
from functools import lru_cache

import pytest

from flockcal.simulator.performer import Performer
from flockcal.solver.slippage.watch import SlipWatch
from slip_scoring import attributes_slip_to
from slip_replay import frames, tree

RATE = 144.0
# Issue 32's promise is 1 s (the frame test needs 0.3 s of frames after the step before it can see it).
WITHIN_S = 1.0
# At 19.69 s of kiosk seed 1 both arms start a slot's first sweep: every upper-body slip there is missed
# within 1 s by the confirming test alone (bench_slip_sweep.py --routines kiosk --seeds 1 --list).
AT = 19.692
# The frame test as docs/slippage.md measures it (the evidence needed, in nats).
FRAME_STEP = (("frame_step", 20.0),)


@lru_cache(maxsize=2)
def _performance(options: tuple) -> tuple[Performer, SlipWatch]:
    perf = Performer("human", routine="kiosk", seed=1, noise="tracker", rate_hz=RATE)
    watch = SlipWatch(tree(perf.model), perf.n_sensors, RATE, perf.names, **dict(options))
    assert watch.feed(*frames(perf, 0.0, AT)) == [], "a false alarm before the slip"
    return perf, watch


def _slip(sensor: str, options: tuple = FRAME_STEP) -> list:
    perf, fed = _performance(options)
    watch = copy.deepcopy(fed)
    perf.clear_faults()
    perf.inject_slip(sensor, 0.02, at_time=AT)
    try:
        return watch.feed(*frames(perf, AT, AT + WITHIN_S))
    finally:
        perf.clear_faults()


@pytest.mark.parametrize("sensor", ["r_upper_arm", "l_upper_arm", "head"])
def test_a_slip_as_the_arms_start_a_new_sweep_is_found_within_a_second(sensor):
    # Two sensors of two joints each (shoulder and elbow: one step in the sensor's frame must explain both)
    # and a leaf (the head: one joint, the neck).
    found = _slip(sensor)
    assert found, f"the {sensor} slip at {AT} s was not found within {WITHIN_S} s"
    first = found[0]
    perf, _ = _performance(FRAME_STEP)
    assert attributes_slip_to(first, sensor, perf.model.names, perf.model.parent), first.to_dict()
    assert first.detected_s - AT <= WITHIN_S and abs(first.time_s - AT) <= 0.05, first.to_dict()


def test_without_the_frame_test_the_confirming_test_alone_misses_it():
    # Tried: the same slip with the frame-rate step test off: no event within the second, which is why the
    # test above holds the frame test and not the confirming test.
    assert _slip("r_upper_arm", (("frame_step", None),)) == []


@pytest.mark.parametrize("seed", [1005, 1000])
def test_a_fresh_kiosk_guest_raises_no_alarm_with_it(seed):
    # Guests of 30 s from the start (every pose new) whose right hand, swinging at up to 6 m/s (tracker
    # noise grows with speed), gave the frame test its highest scores where nothing slipped (14.6 and
    # 12.6 nats against the 20 needed: docs/slippage.md). Taking a window's noise as the median over all of
    # it, without the joint's rotation among the smooth terms, scored 28 nats on such a swing (guest 1017,
    # the hand speeding from 0.5 to 6 m/s inside the window) and would have raised an alarm.
    perf = Performer("human", routine="kiosk", seed=seed, noise="tracker", rate_hz=RATE, seconds=30)
    watch = SlipWatch(tree(perf.model), perf.n_sensors, RATE, perf.names, **dict(FRAME_STEP))
    events = watch.feed(*frames(perf, 0.0, 30.0))
    assert events == [], [e.to_dict() for e in events]
    assert watch.monitor.frame_log, "the frame test did run on this guest's soft tissue"


# Issue 32, fifth round (docs/slippage.md): the frame test scores each sensor from where its own last look
# stopped. A kiosk slip as both arms sweep: the arms' soft tissue raises a suspicion a little before or after
# the slip, the frame test looks at that suspicion's sensors onset by onset, and the slipped sensor's own
# joint crosses the threshold 0.1–0.3 s later and joins it. When a look's onsets counted for the whole
# suspicion, the newcomer was never tested at the onsets already passed, which held the slip's own (the head
# scored 46 nats at its true onset in a one-off replay, the chest 76, against the 20 needed: both missed).
@lru_cache(maxsize=2)
def _kiosk(seed: int, at: float) -> tuple[Performer, SlipWatch]:
    perf = Performer("human", routine="kiosk", seed=seed, noise="tracker", rate_hz=RATE)
    watch = SlipWatch(tree(perf.model), perf.n_sensors, RATE, perf.names, **dict(FRAME_STEP))
    assert watch.feed(*frames(perf, 0.0, at)) == [], "a false alarm before the slip"
    return perf, watch


@pytest.mark.parametrize("seed, at, sensor", [(2, 19.692, "head"), (3, 50.462, "chest")])
def test_a_sensor_whose_joint_joins_a_suspicion_late_is_tested_at_the_slips_own_onset(seed, at, sensor):
    # The head (a leaf: one joint) at the arms' first sweep, and the chest (a hub of four joints, two of them
    # the shoulders, which are sweeping) in the second loop: both missed within 1 s before this change
    # (bench_slip_sweep.py --routines kiosk --seeds 2 3 --list --monitor frame_step=20, 2026-12-05).
    perf, fed = _kiosk(seed, at)
    watch = copy.deepcopy(fed)
    perf.clear_faults()
    perf.inject_slip(sensor, 0.02, at_time=at)
    try:
        found = watch.feed(*frames(perf, at, at + WITHIN_S))
    finally:
        perf.clear_faults()
    assert found, f"the {sensor} slip at {at} s of kiosk seed {seed} was not found within {WITHIN_S} s"
    first = found[0]
    assert attributes_slip_to(first, sensor, perf.model.names, perf.model.parent), first.to_dict()
    # The step is at one frame: the onset the test names is within a few frames of it (0.05 s: 7 frames).
    assert first.detected_s - at <= WITHIN_S and abs(first.time_s - at) <= 0.05, first.to_dict()
