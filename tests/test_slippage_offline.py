"""Slippage on recorded takes (`detect_slips`, and `solve_take`: the re-fit after slips that `flockcal fit`
and session resolve run), exact data, the event JSON and the errors a caller sees for unusable input."""

from __future__ import annotations

import numpy as np
import pytest

from flockcal.simulator.take import simulate
from flockcal.solver.accumulator import GramAccumulator
from flockcal.solver.calibration import calibrate
from flockcal.solver.fits import pair_fits
from flockcal.solver.segments import SegmentedAccumulator
from flockcal.solver.slippage import SlipMonitor, SlippageError, detect_slips
from flockcal.solver.solve import solve_take

SLIP_AT = 12.0


def whole_take_fit(take):
    acc = GramAccumulator(take.n_sensors)
    acc.add_poses(take.rotations, take.positions, take.valid)
    return acc, calibrate(acc, names=take.names)


@pytest.fixture(scope="module")
def slipped_take():
    return simulate(seconds=20, seed=7, faults={"slip": {"sensor": "r_shin", "distance_m": 0.02, "at_time": SLIP_AT}})


def test_recorded_take_slip_found_with_a_whole_take_fit_blended_across_it(slipped_take):
    take, truth = slipped_take
    _, cal = whole_take_fit(take)  # a searched tree; its joints are fitted across the slip
    events = detect_slips(take, cal)
    assert len(events) == 1
    ev = events[0]
    assert ev.sensor == "r_shin" and abs(ev.time_s - SLIP_AT) < 0.1 and 10 < ev.jump_mm < 40
    d = ev.to_dict()
    assert {"time_s", "sensor", "candidates", "joints", "jump_mm"} <= set(d)
    assert set(d["joints"]) == set(truth["slip_events"][0]["joints"])


def test_fit_output_after_a_slip_uses_post_slip_frames_for_the_slipped_sensor_only(slipped_take):
    take, _ = slipped_take
    acc, cal = whole_take_fit(take)
    events = detect_slips(take, cal)
    tree = cal.to_dict()
    whole = calibrate(acc, hierarchy=tree["parent"], root=tree["root"], names=take.names).to_dict()
    out = solve_take(take, events, hierarchy=tree["parent"], root=tree["root"]).to_dict()
    assert [e["sensor"] for e in out["slip_events"]] == ["r_shin"]
    after = GramAccumulator(take.n_sensors, origin=acc.origin)
    keep = take.times >= events[0].time_s
    after.add_poses(take.rotations[keep], take.positions[keep], take.valid[keep])
    by_child = {e["child"]: e for e in whole["joints"]}
    assert sorted(by_child) == sorted(e["child"] for e in out["joints"])
    for entry in out["joints"]:
        before = by_child[entry["child"]]
        pair = [take.index(entry["child"]), take.index(entry["parent"])]
        if "r_shin" in (entry["child"], entry["parent"]):
            # The slipped sensor's joints as the frames since the slip give them; a hinge (the knee) only
            # across its axis: along it the point is the hinge rule's (docs/design.md §3c), which the
            # neighbours' fits move.
            direct = pair_fits(after, [pair])
            for got, want, axis in ((entry["c"], direct.c[0], direct.axis_i[0]), (entry["l"], direct.l[0], direct.axis_j[0])):
                off = np.asarray(got) - want
                if direct.hinge[0]:
                    off = off - (off @ axis) * axis
                np.testing.assert_allclose(off, 0.0, atol=1e-9)
        else:  # the same frames, summed in a different order
            assert (entry["child"], entry["parent"]) == (before["child"], before["parent"])
            np.testing.assert_allclose(entry["c"], before["c"], atol=1e-9)
            np.testing.assert_allclose(entry["l"], before["l"], atol=1e-9)
    touched = {"r_shin", "r_foot"}
    changed = 0
    key = lambda b: (b["body"], b["from_joint"], b["to_joint"])  # noqa: E731
    bones = {key(b): b for b in whole["bones"]}
    for b1 in out["bones"]:
        b0 = bones[key(b1)]
        if touched & {b1["from_joint"], b1["to_joint"]}:
            changed += b1.get("segment_start_s") is not None
        else:
            assert b1["length_m"] == pytest.approx(b0["length_m"], abs=1e-9)
    assert changed >= 1


def test_exact_data_slip_found_and_clean_exact_data_quiet():
    clean, _ = simulate(seconds=16, seed=3, noise=None)
    slipped, _ = simulate(seconds=16, seed=3, noise=None,
                          faults={"slip": {"sensor": "l_upper_arm", "distance_m": 0.02, "at_time": SLIP_AT}})
    _, cal = whole_take_fit(clean)
    assert detect_slips(clean, cal) == []
    events = detect_slips(slipped, cal)
    assert [e.sensor for e in events] == ["l_upper_arm"]


def test_segment_holds_exactly_the_frames_since_the_slip(slipped_take):
    take, _ = slipped_take
    seg = SegmentedAccumulator(take.n_sensors)
    half = len(take.times) // 2
    for a in range(0, len(take.times), 7):  # uneven micro-batches, as a live stream gives
        seg.ingest(take.times[a:a + 7], take.rotations[a:a + 7], take.positions[a:a + 7], take.valid[a:a + 7])
        if a <= half < a + 7:
            s = seg.start_segment(3, take.times[half] - 0.3)
    ref = GramAccumulator(take.n_sensors, origin=seg.whole.origin)
    keep = take.times >= s.base_s
    assert s.base_s >= s.start_s
    ref.add_poses(take.rotations[keep], take.positions[keep], take.valid[keep])
    np.testing.assert_allclose(seg.since(3).gram, ref.gram, rtol=1e-9, atol=1e-9)
    # A copy answers the same and does not move when the original keeps growing.
    frozen = seg.copy()
    seg.ingest(take.times[-1:] + 0.01, take.rotations[-1:], take.positions[-1:])
    np.testing.assert_allclose(frozen.since(3).gram, ref.gram, rtol=1e-9, atol=1e-9)
    assert frozen.frames == seg.frames - 1


def test_bad_input_is_reported_as_a_slippage_error(slipped_take):
    take, _ = slipped_take
    # a joint naming sensor 16 of a 16-sensor suit, and a joint from a sensor to itself
    with pytest.raises(SlippageError, match="distinct sensor indices"):
        SlipMonitor([[16, 0]], 16, 100.0)
    with pytest.raises(SlippageError, match="distinct sensor indices"):
        SlipMonitor([[2, 2]], 16, 100.0)
    # frames of 15 sensors fed to a 16-sensor monitor
    mon = SlipMonitor([[1, 0]], 16, 100.0)
    with pytest.raises(SlippageError, match="rotations"):
        mon.add_frames(np.zeros(2), np.zeros((2, 15, 3, 3)), np.zeros((2, 15, 3)), None, np.zeros((1, 3)), np.zeros((1, 3)))
    # no joint estimates at all
    with pytest.raises(SlippageError, match="c and l"):
        mon.add_frames(np.zeros(1), np.tile(np.eye(3), (1, 16, 1, 1)), np.zeros((1, 16, 3)))
    # neither a calibration nor joints
    with pytest.raises(SlippageError, match="calibration"):
        detect_slips(take)
    # a calibration (§5 dict) for a differently named suit
    other = {"joints": [{"child": "left_knee", "parent": "pelvis", "c": [0, 0, 0], "l": [0, 0, 0]}]}
    with pytest.raises(SlippageError, match="left_knee"):
        detect_slips(take, other)


def test_refit_accepts_stored_events_without_the_event_classes(slipped_take):
    # A session re-solved from its database rows has only time_s and the sensor's index.
    from types import SimpleNamespace

    take, truth = slipped_take
    stored = [SimpleNamespace(kind="slip", time_s=SLIP_AT, sensor_index=take.index("r_shin"))]
    out = solve_take(take, stored, hierarchy=truth["parent"], root=truth["root"]).to_dict()
    refit = sorted(j["child"] for j in out["joints"] if "segment_start_s" in j)
    assert refit == ["r_foot", "r_shin"]
    assert out["slip_events"][0]["time_s"] == SLIP_AT
