"""The confirming test's new-pose rules (docs/slippage.md, "New poses"): slips that land as the limbs
move into a new pose are found within a second and named right with them; they stay off by default,
and the default raises no alarm on a fresh guest those rules report a slip for. The second look
(`second_look`, also off by default) finds such a slip of a leaf, and raises no alarm on a fresh guest
where a re-seated suspicion without its same-pose verdict did.

The cases are the kiosk routine with the simulator's default soft tissue, fed through the live loop
(`SlipWatch`) in the service's 1/30 s micro-batches. Both slips are missed within 1 s without the rules
(a sensor seen through two joints scored without the baseline's extrapolation as noise, a refuted
suspicion re-seated at the slip's own start)."""

from __future__ import annotations

from flockcal.simulator.performer import Performer
from flockcal.solver.slippage.watch import SlipWatch
from slip_replay import first_slip_event, frames, tree

RATE = 144.0
# The promise is 1 s; these slips are found in 0.18-0.40 s here.
WITHIN_S = 1.0
# The options docs/slippage.md ("New poses") measures, off by default for the false alarms they raise
# in fresh kiosk guests (the last test holds the default to none on such a guest).
NEW_POSE_RULES = {"extrapolation_share": (1.0, 0.0, 1.0), "reseat_refuted": True}
# The second look as docs/slippage.md measures it: none of the extrapolation counted for any sensor, a
# slip it names reported only where the same pose before the onset shows the step stayed.
SECOND_LOOK = {"second_look": (0.0, 0.0), "reseat_refuted": True}


def _slipped(sensor: str, at: float, rules: dict = NEW_POSE_RULES):
    # Seed 1 of the kiosk routine (30 s loop): at 48.84 s both arms have just begun their slot's first
    # sweep of the second loop, the pose they held 30 s earlier and not in the 8 s baseline behind them.
    perf = Performer("human", routine="kiosk", seed=1, noise="tracker", rate_hz=RATE)
    watch = SlipWatch(tree(perf.model), perf.n_sensors, RATE, perf.names, **rules)
    first_slip_event(perf, watch, sensor, at, WITHIN_S, 0.1)
    return watch


def test_a_forearm_slip_as_the_arms_move_into_a_new_pose_is_found_within_a_second():
    # A sensor with two joints (elbow, wrist): one step in its own frame must explain both.
    _slipped("l_forearm", 48.842)


def test_an_upper_arm_slip_as_the_arms_move_into_a_new_pose_is_found_within_a_second():
    # The other arm's sensor of two joints (shoulder, elbow), at the same moment.
    _slipped("r_upper_arm", 48.842)


def test_a_fresh_kiosk_guest_raises_no_alarm_by_default():
    # Tried: a guest of 30 s from the start (every pose new), seed 1012, whose right forearm the new-pose
    # rules report at 18.7 s although nothing slipped (9 of 120 such guests had one with them).
    perf = Performer("human", routine="kiosk", seed=1012, noise="tracker", rate_hz=RATE, seconds=30)
    watch = SlipWatch(tree(perf.model), perf.n_sensors, RATE, perf.names)
    events = watch.feed(*frames(perf, 0.0, 30.0))
    assert events == [], [e.to_dict() for e in events]
    assert watch.monitor.confirmations > 0  # the confirming test did run on this guest's soft tissue


def test_the_second_look_finds_a_head_slip_as_the_arms_move_into_a_new_pose():
    # A leaf (one joint): scored counting none of the extrapolation, and reported because the neck and
    # the joints beside it were in the same pose just before the slip with the residual a step away.
    # Without the second look this slip is not found within a second (tried: no event by 1 s).
    _slipped("head", 48.842, SECOND_LOOK)


def test_the_second_look_raises_no_alarm_on_a_fresh_guest_a_reseat_alone_would():
    # Tried: guest 1054 (30 s from the start) with the second look's re-seat of a refuted suspicion but no
    # same-pose verdict on it reported the right hand at 23.04 s (18.8 mm) although nothing slipped.
    perf = Performer("human", routine="kiosk", seed=1054, noise="tracker", rate_hz=RATE, seconds=30)
    watch = SlipWatch(tree(perf.model), perf.n_sensors, RATE, perf.names, **SECOND_LOOK)
    events = watch.feed(*frames(perf, 0.0, 30.0))
    assert events == [], [e.to_dict() for e in events]
    assert watch.monitor.reseated > 0  # the second look did move refuted suspicions on this guest
