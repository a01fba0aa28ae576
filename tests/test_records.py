"""A stored result rebuilds the object it was (issue 33): `Calibration`, `SlipEvent` and `SwapEvent` to JSON
text and back without loss (solver/records.py), for every way a calibration is made: the slip-segmented fit
of a recorded take, a saved-skeleton fit with its warm-start state, an optical fit. The stable `--json`
contract is not this (tests/test_calibration_json.py holds it); a rebuilt calibration must print it alike.
"""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest

from flockcal.exports.skeleton import parse_skeleton, skeleton_dict
from flockcal.simulator import optical as so
from flockcal.simulator.take import simulate
from flockcal.solver.accumulator import GramAccumulator
from flockcal.solver.calibration import Calibration, calibrate
from flockcal.solver.errors import SolverError
from flockcal.solver.optical.pipeline import fit_markers
from flockcal.solver.records import from_record, record_text, to_record
from flockcal.solver.segments import segmented_from_take
from flockcal.solver.slippage import SlipEvent, SwapEvent, detect_slips
from flockcal.solver.solve import solve, solve_take


def assert_same(a, b, where="value"):
    """`b` is `a`: the same types all the way down, arrays of the same dtype and shape and every element
    equal (NaN where NaN, the sign of zero and of infinity kept), floats bit for bit."""
    assert type(a) is type(b), f"{where}: {type(a).__name__} became {type(b).__name__}"
    if dataclasses.is_dataclass(a):
        for f in dataclasses.fields(a):
            assert_same(getattr(a, f.name), getattr(b, f.name), f"{where}.{f.name}")
    elif isinstance(a, np.ndarray):
        assert a.dtype == b.dtype and a.shape == b.shape, f"{where}: {a.dtype}{a.shape} became {b.dtype}{b.shape}"
        assert a.tobytes() == b.tobytes() or (a.dtype.kind == "f" and np.array_equal(a, b, equal_nan=True)
                                               and np.array_equal(np.signbit(a), np.signbit(b))), where
    elif isinstance(a, float):
        assert (math.isnan(a) and math.isnan(b)) or (a == b and math.copysign(1, a) == math.copysign(1, b)), where
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), f"{where}: {len(a)} items became {len(b)}"
        for k, (x, y) in enumerate(zip(a, b)):
            assert_same(x, y, f"{where}[{k}]")
    elif isinstance(a, dict):
        assert list(a) == list(b), f"{where}: keys {list(a)} became {list(b)}"
        for k in a:
            assert_same(a[k], b[k], f"{where}[{k!r}]")
    else:
        assert a == b, f"{where}: {a!r} became {b!r}"


def round_trip(obj):
    text = record_text(obj)
    assert "NaN" not in text and "Infinity" not in text  # strict JSON: a browser or SQLite reads it
    return from_record(json.loads(text))


@pytest.fixture(scope="module")
def slipped():
    """A 20 s simulated take, r_shin slipped 2 cm at 12 s: `flockcal fit`'s path (whole-take fit, slip
    search, the fit segmented at the slips found)."""
    take, _ = simulate(seconds=20, seed=7, faults={"slip": {"sensor": "r_shin", "distance_m": 0.02, "at_time": 12.0}})
    acc = GramAccumulator(take.n_sensors)
    acc.add_poses(take.rotations, take.positions, take.valid)
    events = detect_slips(take, calibrate(acc, names=take.names))
    return take, events, solve_take(take, events)


def test_a_slip_segmented_calibration_comes_back_whole(slipped):
    _, events, cal = slipped
    # What makes this fit more than the stable contract: typed events, segment starts, all-pair fits.
    assert [type(e) for e in cal.slip_events] == [SlipEvent] and cal.fits is not None
    assert np.isfinite(cal.segment_start_s).any() and np.isnan(cal.segment_start_s).any()
    back = round_trip(cal)
    assert_same(cal, back)
    assert json.dumps(back.to_dict()) == json.dumps(cal.to_dict())  # the --json text, alike to the byte


def test_slip_and_swap_events_come_back_with_their_indices_and_unrounded_times(slipped):
    _, events, _ = slipped
    # Tried: the detected event (its §5 entry rounds time_s to 0.1 ms and drops the indices) and a swap
    # not yet reported (detected_s NaN), alone and inside a calibration.
    swap = SwapEvent(12.345678912345, "l_hand", "r_hand", ("l_hand", "r_hand"), 31.25, detected_s=float("nan"),
                     sensor_indices=(6, 9), joint_indices=(5, 8))
    for ev in [*events, swap]:
        back = round_trip(ev)
        assert_same(ev, back)
        assert back.kind == ev.kind and json.dumps(back.to_dict()) == json.dumps(ev.to_dict())
    assert from_record(to_record(swap), expected=(SlipEvent, SwapEvent)).sensor_indices == (6, 9)


def test_a_saved_skeleton_fit_comes_back_with_the_state_the_next_refresh_starts_from(slipped):
    take, events, _ = slipped
    whole = GramAccumulator(take.n_sensors)
    whole.add_poses(take.rotations, take.positions, take.valid)
    skeleton = parse_skeleton(json.loads(json.dumps(skeleton_dict(calibrate(whole, names=take.names)))))
    acc = segmented_from_take(take, events)
    first = solve(acc, take.names, skeleton=skeleton, slip_events=events)
    assert first.known_skeleton and first.state is not None and first.rms_free is not None
    back = round_trip(first)
    assert_same(first, back)
    # The rebuilt result warm-starts the next fit exactly as the one kept in memory does.
    assert_same(solve(acc, take.names, skeleton=skeleton, previous=first),
                solve(acc, take.names, skeleton=skeleton, previous=back))


def test_an_optical_fit_comes_back_with_its_markers_and_decisions():
    model = so.rods((0.45, 0.50, 0.45), seed=7)
    take, _ = so.simulate_markers(model, so.rod_motion(model, 15, 60, 7), per_body=(2, 3), noise_m=0.001, seed=7)
    cal = fit_markers(take.markers, take.marker_names, take.rate_hz).calibration()
    assert cal.optical is not None
    back = round_trip(cal)
    assert_same(cal, back)
    assert json.dumps(back.to_dict()) == json.dumps(cal.to_dict())


def test_non_finite_numbers_and_keys_that_are_not_strings_survive():
    # Tried: what JSON cannot say as it stands — NaN, ±inf, −0.0 in arrays and alone, an empty (0, 3)
    # array, integer and tuple dict keys, a key that looks like the record's own tags.
    swap = SwapEvent(-0.0, "a", "b", (), float("inf"), confidence=float("-inf"))
    assert_same(swap, round_trip(swap))
    cal = Calibration(("a", "b"), 0, np.array([-1, 0]), np.array([0, 1]), 0,
                      None, None, np.array([[np.nan, np.inf, -0.0], [-np.inf, 1e-310, 2.0]]),
                      loop_candidates=[(0, 1, float("nan"))], ambiguous=[(1, [0], "note")],
                      slip_events=({"$type": "a stored dict", 3: "x", ("a", 1): None},),
                      segment_start_s=np.zeros((0, 3)))
    assert_same(cal, round_trip(cal))


@pytest.mark.parametrize("record, says", [
    ("{not json", "not JSON"),
    ({"joints": []}, "not a flockcal record"),
    ({"$record": 99, "value": None}, "version 99"),
    ({"$record": 1, "value": {"$type": "os.system"}}, "unknown type 'os.system'"),
    ({"$record": 1, "value": {"$array": "object", "shape": [1], "data": [1]}}, "dtype object"),
    ({"$record": 1, "value": {"$array": "float64", "shape": [2, 3], "data": [1.0]}}, "damaged"),
    ({"$record": 1, "value": {"$type": "SwapEvent", "time_s": 1.0}}, "damaged"),
])
def test_a_record_that_is_not_one_is_refused_in_one_line(record, says):
    with pytest.raises(SolverError, match=says) as info:
        from_record(record)
    assert "\n" not in str(info.value)


def test_a_record_of_another_type_is_refused_when_a_type_is_expected(slipped):
    _, events, _ = slipped
    with pytest.raises(SolverError, match="holds a SlipEvent, not a Calibration"):
        from_record(record_text(events[0]), expected=Calibration)


def test_a_stored_slip_entry_becomes_the_event_again_to_its_rounding(slipped):
    # The service stores each event's §5 entry with its kind under "type" and re-solves a session from
    # them (server/sessions.py): the typed event comes back, to the entry's rounding, its sensor index
    # from the take's names. Tried also: a swap, an entry naming no sensor of the take, one with no time.
    from flockcal.solver.calibration_json import event_from_json

    take, events, _ = slipped
    for ev in events:
        stored = json.loads(json.dumps(ev.to_dict()))
        stored["type"] = stored.pop("kind")
        back = event_from_json(stored, take.names)
        assert type(back) is SlipEvent and back.sensor_index == ev.sensor_index == take.names.index(ev.sensor)
        assert back.to_dict() == ev.to_dict() and abs(back.time_s - ev.time_s) <= 5e-5
    swap = SwapEvent(3.25, "l_hand", "r_hand", ("l_hand",), 25.0, detected_s=3.5, sensor_indices=(6, 9))
    back = event_from_json(json.loads(json.dumps(swap.to_dict())), take.names)
    assert type(back) is SwapEvent and back.sensor_indices == (take.names.index("l_hand"), take.names.index("r_hand"))
    assert back.to_dict() == swap.to_dict()
    with pytest.raises(SolverError, match=r"names sensor\(s\) 'nobody', not one of the take's"):
        event_from_json({"type": "slip", "time_s": 1.0, "sensor": "nobody"}, take.names)
    with pytest.raises(SolverError, match="lacks 'time_s'"):
        event_from_json({"type": "slip", "sensor": "head"}, take.names)
