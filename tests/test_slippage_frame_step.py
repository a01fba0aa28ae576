"""The frame-rate step test (docs/slippage.md, "Fourth round" to "Seventh round"; on by default since the
sixth): a slip that lands as the limbs start a sweep they have not made before, where the confirming test's
pose model extrapolates and refutes it, is found from the frames around it alone (a step shared by every
joint of the sensor, in its own frame, against a cubic in time and the joint's own rotation, its noise at
least what the joint's speed makes it), and fast hands where nothing slipped raise no alarm with it. Since
the seventh round it scans every sensor at every onset, not only the sensors of the step test's suspicions.

The cases are the kiosk routine, seed 1, with the simulator's default soft tissue, fed through the live
loop (`SlipWatch`) in the service's 1/30 s micro-batches; slips are scheduled in the performance's own
time (the simulator's clock), so load cannot move them."""

from __future__ import annotations

import copy
from functools import lru_cache

import numpy as np
import pytest

from flockcal.simulator.performer import Performer
from flockcal.solver.slippage.framestep import frame_steps, noise_law
from flockcal.solver.slippage.stats import joint_geometry
from flockcal.solver.slippage.watch import SlipWatch
from slip_scoring import attributes_slip_to
from slip_replay import first_slip_event, frames, tree

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


# Issue 32, fifth round (docs/slippage.md): a kiosk slip as both arms sweep, where the arms' soft tissue
# raises a suspicion a little before or after the slip and the slipped sensor's own joint crosses the step
# test's threshold 0.1–0.3 s later. When the frame test looked only at a suspicion's sensors and counted a
# look's onsets for the whole suspicion, the newcomer was never tested at the onsets already passed, which
# held the slip's own (the head scored 46 nats at its true onset in a one-off replay, the chest 76, against
# the 20 needed: both missed). The scan of the seventh round tests every sensor at every onset.
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


# The frame test's noise against speed (docs/slippage.md, "Sixth round"): a magnetic tracker's error grows
# with the sensor's speed, and a step estimate leans on the frames around its onset, where a swinging
# limb is fastest. Measured over a window's second differences alone, the noise there came out too low.
def test_the_noise_law_recovers_noise_that_grows_with_speed():
    # Tried: two sensors at one joint centre (c = l = 0) swinging together at 0-5 m/s on a 1 m circle,
    # each one's position noise 1.5 mm per axis plus 2.5 mm per m/s (added in quadrature), 60 s at 144 Hz;
    # the law is fitted to the joint residual's second differences. The oracle: the noise actually added,
    # frame by frame, against the true speed (the residual carries both sensors' noise).
    rate, n = 144.0, 144 * 60
    rng = np.random.default_rng(7)
    time = np.arange(n) / rate
    phase = 2.0 * np.sin(2 * np.pi * 0.2 * time) + 0.8 * np.sin(2 * np.pi * 0.53 * time)
    path = np.stack([np.sin(phase), np.cos(phase), np.zeros(n)], axis=-1)  # metres
    speed = np.linalg.norm(np.gradient(path, axis=0) * rate, axis=-1)
    sd = np.sqrt(0.0015**2 + (0.0025 * speed) ** 2)
    noisy = path[:, None, :] + sd[:, None, None] * rng.standard_normal((n, 2, 3))
    R = np.broadcast_to(np.eye(3), (n, 2, 3, 3))
    joints = np.array([[1, 0]])
    g, Q = joint_geometry(R, noisy, joints)
    a, b = noise_law(g, Q, noisy, np.ones((n, 1), dtype=bool), np.zeros((1, 3)), np.zeros((1, 3)), joints)
    # The law's speed term is both sensors' squared displacement over 4 frames, 2 (4 v / rate)².
    law_sd = np.sqrt(a[0] + b[0] * 2.0 * (4.0 * speed / rate) ** 2)
    true_sd = np.sqrt(2.0) * sd
    slow, fast = speed < 0.5, speed > 3.5
    assert slow.sum() > 500 and fast.sum() > 500
    # 15 %: the law is fitted, not given (two parameters from 8,640 frames; the speed term itself noisy).
    assert law_sd[slow].mean() == pytest.approx(true_sd[slow].mean(), rel=0.15)
    assert law_sd[fast].mean() == pytest.approx(true_sd[fast].mean(), rel=0.15)


def test_a_fast_hand_in_the_walk_hour_raises_no_alarm():
    # Tried: the walk hour's soak (seed 11, the default soft tissue, 144 Hz) from 2330 s: at 2397.42 s the
    # right hand swings from 0.7 to 5.5 m/s and back inside the test's window, and ten frames of its tracker
    # noise lie 1-2 standard deviations one way. Against a window's own noise level the frame test scored a
    # 36 mm step there at 24.6 nats, a false alarm; against the hand's noise law it scores under 10.
    perf = Performer("human", routine="walk", seed=11, noise="tracker", rate_hz=RATE, seconds=3600.0,
                     period=3600.0, sta_mm=12.0)
    watch = SlipWatch(tree(perf.model), perf.n_sensors, RATE, perf.names, **dict(FRAME_STEP))
    events = watch.feed(*frames(perf, 2330.0, 2400.0))
    assert events == [], [e.to_dict() for e in events]
    hand = [r for r in watch.monitor.frame_log if r[1] == "r_hand" and abs(r[0] - 2397.42) < 0.05]
    assert hand, "the frame test looked at the right hand's swing"
    # The margin: half the evidence the test needs (it scored 7.4 when this was written).
    assert max(r[2] for r in hand) < 0.5 * FRAME_STEP[0][1]


def test_the_confirming_test_sees_the_same_with_the_frame_test_on_or_off():
    # Tried: a fresh kiosk guest (seed 1000, 30 s, nothing slipped) with the frame test on and off. The frame
    # test keeps nothing in the confirming test's list (four at most): when refuted suspicions waited there
    # for it, they took the hits of a slip's own onset, and the new-pose rules' upper arm at 48.84 s
    # (tests/test_slippage_new_poses.py) was missed with the frame test on.
    runs = {}
    for option in (None, FRAME_STEP[0][1]):
        perf = Performer("human", routine="kiosk", seed=1000, noise="tracker", rate_hz=RATE, seconds=30)
        watch = SlipWatch(tree(perf.model), perf.n_sensors, RATE, perf.names, frame_step=option)
        assert watch.feed(*frames(perf, 0.0, 30.0)) == []
        runs[option] = (watch.monitor.confirmations, watch.monitor.reseated, len(watch.monitor.frame_log))
    off, on = runs[None], runs[FRAME_STEP[0][1]]
    assert on[:2] == off[:2] and off[0] > 50, runs
    assert off[2] == 0 and on[2] > 0, "the frame test looked only when on"


# Issue 32, seventh round (docs/slippage.md): slips whose sensor the step test raised no suspicion on near the
# onset, so that the frame test, which then looked only at a suspicion's sensors, never scored them, though
# their frames show the step plainly (one-off replays on 2026-12-05: 40.8 and 30.6 nats at the true onsets).
# Exercise seed 2's head at 31.23 s is the routine's known weak moment (the slot change at 30 s).
@pytest.mark.parametrize("routine, seed, at, sensor", [("kiosk", 2, 18.41, "r_upper_arm"),
                                                       ("exercise", 2, 31.231, "head")])
def test_a_slip_the_step_test_raised_nothing_on_is_found_by_the_scan(routine, seed, at, sensor):
    watch, first = _first_event(routine, seed, at, sensor)
    assert watch.monitor.frame_steps >= 1, "found by the frame test"


def _first_event(routine: str, seed: int, at: float, sensor: str):
    """The live loop (the default frame test) fed from the start, `sensor` slipped 2 cm at `at`: the watch
    and its first event, which must name `sensor` within `WITHIN_S` at an onset within 0.05 s."""
    perf = Performer("human", routine=routine, seed=seed, noise="tracker", rate_hz=RATE)
    watch = SlipWatch(tree(perf.model), perf.n_sensors, RATE, perf.names, **dict(FRAME_STEP))
    return watch, first_slip_event(perf, watch, sensor, at, WITHIN_S, 0.05)


def test_where_the_step_test_raised_nothing_a_frame_step_needs_more():
    # Tried: the kiosk hour's soak (seed 11, the default soft tissue, nothing slipped) around 2782.88 s, where
    # the right upper arm's tracker noise gave the scan its highest score of the hour (17.9 nats for a 17 mm
    # step, shoulder and elbow agreeing) with no step-test hit on its joints near it. With both thresholds
    # lowered to 17 the scan raises an alarm there; with the one near hits lowered alone it does not: what
    # holds it is `frame_step_alone` (25 by default, 20 near hits: the hour's 17.9 would leave 2 nats).
    perf = Performer("human", routine="kiosk", seed=11, noise="tracker", rate_hz=RATE, seconds=3600.0,
                     sta_mm=12.0)
    events = {}
    for alone in (25.0, 17.0):
        watch = SlipWatch(tree(perf.model), perf.n_sensors, RATE, perf.names, frame_step=17.0,
                          frame_step_alone=alone)
        events[alone] = watch.feed(*frames(perf, 2757.0, 2784.0))
    assert events[25.0] == [], [e.to_dict() for e in events[25.0]]
    assert [e.sensor for e in events[17.0]] == ["r_upper_arm"], [e.to_dict() for e in events[17.0]]


def test_a_forearm_slip_its_hand_scores_highest_is_found_and_named_the_forearm():
    # Tried: kiosk seed 2's left forearm slipped 2 cm at 19.69 s, no step-test hit on its joints near the
    # onset. The hand, seen through its one joint (the wrist), scored the wrist's step highest (21.5 nats, a
    # 36 mm step in its own frame): short of the 25 asked where no hit is near, and when 20 was asked
    # everywhere the hand was named, though a hand's slip cannot move the elbow. The forearm's elbow alone
    # shows a step passing the frame test at the same onset: found, and named the forearm, the hand the
    # other candidate (missed by the code before).
    _, first = _first_event("kiosk", 2, AT, "l_forearm")
    assert first.candidates[:2] == ("l_forearm", "l_hand"), first.to_dict()


def test_every_sensor_scored_at_once_scores_each_as_alone():
    # The scan scores all sensors in one pass, each gathering its joints' windows from arrays worked out once
    # per joint in both frames; asked for one sensor at a time (and with a joint left out, as after an
    # event), each must get the same best step. Tried on the kiosk guest's buffer just before the slip moment.
    _, watch = _performance(FRAME_STEP)
    mon, buf = watch.monitor, watch.monitor._buf
    rows = slice(buf.lo, buf.hi)
    c, l = watch.fits.c, watch.fits.l
    law = noise_law(buf.g[rows], buf.Q[rows], buf.t[rows], buf.pv[rows], c, l, mon.joints)
    ready = mon.ready.copy()
    ready[4] = False  # one joint not watched (as after an event): its two sensors have one joint fewer
    n = buf.hi - buf.lo
    args = (buf.g[rows], buf.Q[rows], buf.pv[rows], c, l, mon.joints)
    tail = (n - 200, n - mon._half + 1, mon._half, mon.settings.scale_floor_m, mon._contrast, buf.t[rows], law)
    together = {f.sensor: f for f in frame_steps(*args, range(watch.n_sensors), ready, *tail)}
    assert len(together) >= 12
    for s, f in together.items():
        (alone,) = frame_steps(*args, [s], ready, *tail)
        assert (alone.onset, list(alone.joints)) == (f.onset, list(f.joints))
        assert alone.score == pytest.approx(f.score, rel=1e-9, abs=1e-9)
        assert np.allclose(alone.step, f.step, rtol=1e-9, atol=1e-12)
