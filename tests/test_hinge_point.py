"""A hinge's centre on its axis (issue #36, docs/design.md §3c): where the limb's bones meet the axis when
the neighbouring joints are determined, else the minimum-norm point; one rule for every fit, steady as the
take grows. Oracles: the simulator's own body (its joint centres and axes), never the solver's constants.
"""

from __future__ import annotations

import numpy as np
import pytest

from flockcal.simulator import body as bodies
from flockcal.simulator.performer import Performer
from flockcal.solver.accumulator import GramAccumulator
from flockcal.solver.calibration import calibrate
from synthetic import articulated

RATE = 100.0


def _truth(perf: Performer) -> dict:
    """{frozenset(child, parent): (child, c, l, axis in the child's frame or None)} from the simulator."""
    return {frozenset((j["child"], j["parent"])): (j["child"], np.array(j["c"]), np.array(j["l"]),
                                                   np.array(j["axis_child"]) if j["hinge"] else None)
            for j in perf.truth()["joints"]}


def _along(cal, truth: dict) -> dict:
    """Each true hinge the fit found as a hinge: (its centre's offset along the true axis, m; the rule's name)."""
    out = {}
    d = cal.to_dict()
    for j in d["joints"]:
        key = frozenset((j["child"], j["parent"]))
        if key not in truth or truth[key][3] is None or not j["hinge"]:
            continue
        child, c, l, axis = truth[key]
        got = np.array(j["c"] if j["child"] == child else j["l"])
        out[child] = (float((got - c) @ axis), j["hinge_point"]["rule"])
    return out


def _fit(perf: Performer, seconds: float, start: float = 0.0, acc=None):
    acc = acc or GramAccumulator(perf.n_sensors)
    times = np.arange(int(round(start * RATE)), int(round(seconds * RATE))) / RATE
    R, p, v = perf.poses(times)
    acc.add_poses(R, p, v)
    return calibrate(acc, names=perf.names), acc


def test_on_exact_motion_knees_and_elbows_sit_where_the_limb_bones_meet_their_axes():
    # Rigid sensors, no noise: every neighbouring joint exact. The simulated knee axis is tilted ~2° at
    # random and the elbow's ~5° more along the limb (a carrying angle), and an upper arm is longer than
    # a forearm: the plain mean of the two feet then sits ~8 mm off this body's elbows, the point from
    # which both bones make the same angle with the axis (docs/design.md §3c) within 0.8 mm of every
    # elbow and knee of 10 bodies (benchmarks/bench_hinge_point.py --sta-mm 0). Held at 2 mm.
    perf = Performer("human", routine="exercise", seed=24, noise=None, sta_mm=0, rate_hz=RATE, seconds=60)
    cal, _ = _fit(perf, 60.0)
    got = _along(cal, _truth(perf))
    assert set(got) == {"l_forearm", "r_forearm", "l_shin", "r_shin"}, got
    assert all(rule == "two_bones" for _, rule in got.values()), got
    for child, (along, _) in got.items():
        assert abs(along) < 2e-3, (child, along)


def test_a_lone_hinge_keeps_the_minimum_norm_point_of_its_axis():
    # Two bodies only: no neighbouring joint, so no bone to meet the axis; the point is the one closest to
    # the sensor origins (c·a_c + l·a_p = 0), and the JSON says so.
    d = articulated(m=2, n=600, seed=13, joint_types=["root", "hinge"], offset_scale=0.1)
    acc = GramAccumulator(2).add_poses(d.rotations, d.positions)
    j = calibrate(acc).to_dict()["joints"][0]
    assert j["hinge"] and j["hinge_point"] == {"rule": "min_norm", "data_share": 0.0}
    assert abs(np.dot(j["c"], j["axis_child"]) + np.dot(j["l"], j["axis_parent"])) < 1e-9


def test_a_knee_above_a_hinged_ankle_is_placed_from_the_hip_and_the_ankles_axis_then_the_ankle_from_the_knee():
    # A chain of two hinges (issue #50): the ankle's point on its axis is as open as the knee's, so it
    # cannot place the knee; its axis can: the shank meets it at right angles. The knee sits where the
    # thigh (to the hip's centre) and the shank make the same angle with the knee's axis; the ankle then
    # by the knee (the foot is a leaf: no bone). Oracle: the simulator's body, whose legs are straight at
    # rest and whose ankle axes are square to the shank: the true knee centre, then the foot of it on the
    # true ankle axis (shank frame), which is the true ankle. Exact data: 1 mm. The hip alone (the rule
    # before) left these knees 24.4 and 6.3 mm off: the knee axis's own tilt times the thigh's length.
    perf = Performer(bodies.with_hinges(bodies.human(seed=3), ("foot",)), routine="exercise", seed=3, noise=None,
                     sta_mm=0, rate_hz=RATE, seconds=60)
    cal, _ = _fit(perf, 60.0)
    got = _along(cal, _truth(perf))
    true = {j["child"]: j for j in perf.truth()["joints"]}
    for side in "lr":
        knee, ankle = true[f"{side}_shin"], true[f"{side}_foot"]
        ankle_along = np.array(ankle["axis_parent"]) @ (np.array(knee["c"]) - np.array(ankle["l"]))
        assert got[f"{side}_shin"][1] == "bone_and_axis" and got[f"{side}_foot"][1] == "one_bone", got
        assert abs(got[f"{side}_shin"][0]) < 1e-3, got
        assert abs(got[f"{side}_foot"][0] - ankle_along) < 1e-3, (got, ankle_along)


@pytest.mark.parametrize("seed", [1, 2])
def test_elbows_and_knees_beside_hinged_wrists_and_ankles_sit_at_their_centres(seed):
    # Issue #50: where wrists and ankles are hinges too, an elbow's forearm and a knee's shank end at a
    # centre the data leave anywhere on an axis; the shoulder or hip alone left these bodies' elbows
    # 10.7–31.3 mm and knees 3.7–9.6 mm off (the axis's tilt along the limb times the upper arm or thigh).
    # Rigid sensors with the tracker's noise, 20 s of the kiosk routine: docs/solver.md claims every elbow
    # and knee within 3.7 mm of its true centre along the axis from 20 s on (bench_hinge_point.py
    # --hinged); held at 5 mm, 1.3 mm for bodies the benchmark did not see.
    perf = Performer(bodies.with_hinges(bodies.human(seed=seed)), routine="kiosk", seed=seed, sta_mm=0,
                     rate_hz=RATE, seconds=60)
    cal, _ = _fit(perf, 20.0)
    got = _along(cal, _truth(perf))
    limbs = {"l_forearm", "r_forearm", "l_shin", "r_shin"}
    assert limbs <= set(got), got
    for child in limbs:
        along, rule = got[child]
        assert rule == "bone_and_axis", (child, got)
        assert abs(along) <= 0.005, (seed, child, along)


@pytest.mark.parametrize("seed", [20, 21, 23])
def test_under_soft_tissue_a_hinge_stays_put_once_the_routine_has_run(seed):
    # Issue #36: with the simulator's default 12 mm soft tissue, once the kiosk routine (a 30 s loop) has
    # run once, each elbow and knee moves by at most 3 mm as the take grows, unless one of its neighbours
    # has just become determined (the rule then uses one more bone). Held with a margin of 1 mm.
    perf = Performer("human", routine="kiosk", seed=seed, rate_hz=RATE, seconds=60)
    assert perf.sta_mm > 0
    truth = _truth(perf)
    cal, acc = _fit(perf, 30.0)
    seen = [_along(cal, truth)]
    for t in (40.0, 50.0, 60.0):
        cal, acc = _fit(perf, t, start=t - 10.0, acc=acc)
        seen.append(_along(cal, truth))
    for child in seen[-1]:
        runs: dict[str, list[float]] = {}
        for fit in seen:
            if child in fit:
                runs.setdefault(fit[child][1], []).append(fit[child][0])
        for rule, values in runs.items():
            assert max(values) - min(values) <= 0.004, (seed, child, rule, values)
        # Within the 12 mm of the truth along the axis at the end (median target 5 mm: the benchmark).
        assert abs(seen[-1][child][0]) <= 0.012, (seed, child, seen[-1][child])
