"""`solve`: the one place that picks plain, slip-segmented or saved-skeleton fitting, on either accumulator."""

import numpy as np
import pytest

from flockcal.exports.skeleton import parse_skeleton, skeleton_dict
from flockcal.solver.accumulator import GramAccumulator
from flockcal.solver.accumulator_protocol import Accumulator
from flockcal.solver.calibration import Calibration, calibrate
from flockcal.solver.segments import SegmentedAccumulator
from flockcal.solver.solve import solve
from synthetic import articulated


@pytest.fixture(scope="module")
def data():
    d = articulated(m=5, n=600, seed=7, joint_types=["root", "ball", "hinge", "ball", "ball"])
    times = np.arange(d.rotations.shape[0]) / d.rate_hz
    return d, times


def _fed(d, times, acc):
    return acc.ingest(times, d.rotations, d.positions, None)


def test_both_accumulators_satisfy_the_protocol_and_sum_the_same_frames(data):
    d, times = data
    plain, seg = _fed(d, times, GramAccumulator(5)), _fed(d, times, SegmentedAccumulator(5))
    assert isinstance(plain, Accumulator) and isinstance(seg, Accumulator)
    assert plain.whole_take is plain and not plain.segments and plain.pair_view() is plain
    # The same frames fed through ingest give the same sums whichever accumulator; only rounding differs
    # (the segmented one sums in pieces between its snapshots): 1e-12 of the largest entry.
    scale = np.abs(plain.gram).max()
    assert np.allclose(plain.gram, seg.whole_take.gram, rtol=0, atol=1e-12 * scale)
    assert plain.frames == seg.frames == len(times)
    copy = seg.copy()
    seg.ingest(times[-1:] + 1.0, d.rotations[-1:], d.positions[-1:])
    assert copy.frames == len(times) and seg.frames == len(times) + 1  # the copy did not grow


def test_plain_solve_is_calibrate(data):
    d, times = data
    acc = _fed(d, times, GramAccumulator(5))
    got, want = solve(acc, d.names), calibrate(acc, names=d.names)
    assert isinstance(got, Calibration) and got.to_dict() == want.to_dict()


def test_segmented_solve_refits_the_slipped_sensor_and_says_from_when(data):
    d, times = data
    seg = _fed(d, times, SegmentedAccumulator(5))
    seg.start_segment(3, times[300])
    cal = solve(seg, d.names, hierarchy={d.names[i]: d.names[d.parent[i]] for i in range(1, 5)})
    marked = {d.names[c] for c, s in zip(cal.joint_child, cal.segment_start_s) if np.isfinite(s)}
    # Sensor 3's joints (to its parent, and to any child) use the frames since; the others the whole take.
    touching = {d.names[c] for c in range(1, 5) if 3 in (c, d.parent[c])}
    assert marked == touching and len(touching) < 4
    assert cal.to_dict()["joints"][0].get("segment_start_s") is None


def test_saved_skeleton_solve_keeps_the_bones_and_warm_starts(data):
    d, times = data
    acc = _fed(d, times, GramAccumulator(5))
    free = calibrate(acc, names=d.names)
    skeleton = parse_skeleton(skeleton_dict(free))
    cold = solve(acc, d.names, skeleton=skeleton)
    warm = solve(acc, d.names, skeleton=skeleton, previous=cold)
    assert cold.known_skeleton and cold.to_dict()["known_skeleton"] is True
    # Bones are the saved ones (rounding only): the fit moves placements, never lengths.
    saved = {(b["from_joint"], b["to_joint"]): b["length_m"] for b in skeleton.data["bones"]}
    got = {(b["from_joint"], b["to_joint"]): b["length_m"] for b in cold.to_dict()["bones"]}
    assert got.keys() == saved.keys() and all(abs(got[k] - saved[k]) < 1e-9 for k in got)
    # A refresh from the last result lands on the same placements (exact data: to rounding, 1e-9 m).
    assert warm.state is not cold.state and np.allclose(warm.joints.c, cold.joints.c, rtol=0, atol=1e-9)
