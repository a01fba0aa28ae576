"""Promises of calibrate(): bones and placement to 1e-9 m on exact data, the given-hierarchy path, the §5 JSON."""

import json

import numpy as np
import pytest

from flockcal.solver.accumulator import GramAccumulator
from flockcal.solver.calibration import calibrate, parse_hierarchy
from flockcal.solver.errors import SolverError
from residuals import joint_residuals
from flockcal.rotations import nearest_rotation
from kinematics import to_global, to_local
from synthetic import articulated


@pytest.fixture(scope="module")
def exact():
    d = articulated(m=7, n=500, seed=31, dropout=0.05)
    return d, GramAccumulator(7).add_poses(d.rotations, d.positions, d.valid)


def _bone_table(b):
    return {(int(x), int(f), int(t)): L for x, f, t, L in zip(b.body, b.from_joint, b.to_joint, b.length)}


def test_bone_lengths_and_joints_match_the_truth_to_1e9_m(exact):
    d, acc = exact
    cal = calibrate(acc, root=0, names=d.names)
    assert np.array_equal(cal.parent, d.parent)
    child = cal.joint_child
    assert np.abs(cal.c - d.c[child]).max() < 1e-9 and np.abs(cal.l - d.l[child]).max() < 1e-9
    truth = {(b, f, t): L for b, f, t, L in d.bones()}
    got = _bone_table(cal.bones)
    assert got.keys() == truth.keys()
    assert max(abs(got[k] - truth[k]) for k in truth) < 1e-9
    assert np.allclose(cal.placement[child], d.c[child], atol=1e-9) and np.isnan(cal.placement[0]).all()


def test_given_hierarchy_fits_only_its_joints_and_agrees_with_the_search(exact):
    d, acc = exact
    searched = calibrate(acc, root=0, names=d.names)
    given = calibrate(acc, hierarchy={d.names[i]: d.names[d.parent[i]] for i in range(1, 7)}, names=d.names)
    assert given.fits is None and given.hierarchy_given
    assert given.root == 0 and np.array_equal(given.parent, d.parent)
    assert np.allclose(given.c, searched.c, atol=1e-12)
    assert _bone_table(given.bones).keys() == _bone_table(searched.bones).keys()


def test_rigid_member_gets_its_placement_and_the_body_keeps_its_bones():
    d = articulated(m=4, n=400, seed=32, joint_types=["root", "ball", "rigid", "ball"], parent=[-1, 0, 1, 2])
    cal = calibrate(GramAccumulator(4).add_poses(d.rotations, d.positions), root=0)
    # Body {1, 2} is one rigid body: joint 1 (to 0) and joint 3 (to 2); its bone is |c_1 − l_3| in a member's frame.
    assert cal.rigid_groups == [[1, 2]]
    entry = 1 if 1 in cal.joint_child else 2
    assert len(cal.bones) == 1 and cal.bones.body[0] == entry
    R1, R2 = d.rotations[0, 1], d.rotations[0, 2]
    joint1_world = R1 @ d.c[1] + d.positions[0, 1]
    joint3_world = R2 @ d.l[3] + d.positions[0, 2]
    assert abs(cal.bones.length[0] - np.linalg.norm(joint1_world - joint3_world)) < 1e-9
    member = 3 - entry
    want = d.rotations[0, member].T @ (joint1_world - d.positions[0, member])
    assert np.allclose(cal.placement[member], want, atol=1e-9)


def test_to_dict_is_exactly_the_section_5_json(exact):
    d, acc = exact
    out = calibrate(acc, names=d.names).to_dict()
    assert list(out)[:8] == ["sensors", "root", "parent", "frames", "joints", "bones", "loop_candidates", "slip_events"]
    assert out["slip_events"] == [] and out["frames"] == 500 and out["sensors"] == list(d.names)
    joint_keys = ["child", "parent", "c", "l", "rms_m", "epsilon", "singular_values", "hinge", "axis_child",
                  "axis_parent", "coverage", "c_stderr_m", "l_stderr_m"]
    # §5's keys first, in order; then the extensions (design.md §3a).
    assert all(list(j)[:13] == joint_keys for j in out["joints"]) and len(out["joints"]) == 6
    assert all(list(j)[13:] == ["determined", "direction_error_m", "noise_error_m", "name"] and j["determined"]
               for j in out["joints"])
    # Issue 47's extensions close the object: no humanoid was looked for (no frames given), and it says so.
    assert list(out)[-3:] == ["humanoid", "humanoid_note", "humanoid_conflicts"] and out["humanoid"] is None
    assert all(list(b) == ["body", "from_joint", "to_joint", "length_m", "stderr_m"] for b in out["bones"])
    assert all(len(j["singular_values"]) == 6 and len(j["coverage"]) == 3 for j in out["joints"])
    json.loads(json.dumps(out, allow_nan=False))  # no NaN or inf anywhere
    assert calibrate(acc, names=d.names).to_dict(slip_events=[{"time_s": 1.0}])["slip_events"] == [{"time_s": 1.0}]


@pytest.mark.parametrize(
    "hierarchy, message",
    [
        ({"b1": "b0", "b2": "nobody"}, "unknown sensor"),
        ({"b1": "b2", "b2": "b1", "b3": "b0", "b4": "b0", "b5": "b0", "b6": "b0"}, "cycle"),
        ({"b1": "b0", "b2": "b0"}, "no parent"),
        ({"b0": None, "b1": None}, "root is given twice"),
        ({"b1": "b1"}, "its own parent"),
    ],
    ids=["unknown name", "cycle", "not covering every sensor", "two explicit roots", "self parent"],
)
def test_bad_hierarchies_are_refused_naming_the_problem(hierarchy, message):
    # Tried: each kind of hierarchy that is not one tree over the take's sensors.
    with pytest.raises(SolverError, match=message):
        parse_hierarchy(hierarchy, tuple(f"b{i}" for i in range(7)))


def test_root_that_disagrees_with_the_hierarchy_is_refused(exact):
    # Tried: --root naming a sensor that the hierarchy gives a parent.
    d, acc = exact
    with pytest.raises(SolverError, match="disagrees"):
        calibrate(acc, hierarchy={d.names[i]: d.names[d.parent[i]] for i in range(1, 7)}, root="b3", names=d.names)


def test_joint_residuals_are_zero_on_exact_data_and_nan_where_a_sensor_is_missing(exact):
    d, _ = exact
    e = joint_residuals(d.rotations, d.positions, d.c[d.joints[:, 0]], d.l[d.joints[:, 0]], d.joints, valid=d.valid)
    both = d.valid[:, d.joints[:, 0]] & d.valid[:, d.joints[:, 1]]
    assert e.shape == (500, 6, 3)
    assert np.abs(e[both]).max() < 1e-12 and np.isnan(e[~both]).all()


def test_nearest_rotation_projects_noisy_tracker_matrices_onto_rotations():
    rng = np.random.default_rng(1)
    d = articulated(m=2, n=50, seed=33)
    noisy = d.rotations + rng.normal(0, 1e-3, d.rotations.shape)
    R = nearest_rotation(noisy)
    assert np.allclose(R @ np.swapaxes(R, -1, -2), np.eye(3), atol=1e-12)
    assert np.allclose(np.linalg.det(R), 1.0)
    assert np.abs(R - d.rotations).max() < 5e-3
    assert np.allclose(nearest_rotation(d.rotations), d.rotations, atol=1e-12)


def test_hierarchical_poses_compose_into_the_global_ones_and_back(exact):
    d, _ = exact
    full = articulated(m=7, n=50, seed=31)
    Rl, tl = to_local(full.rotations, full.positions, full.parent)
    Rg, tg = to_global(Rl, tl, full.parent)
    assert np.allclose(Rg, full.rotations, atol=1e-12) and np.allclose(tg, full.positions, atol=1e-12)
    with pytest.raises(SolverError, match="cycle"):
        to_global(Rl, tl, np.array([-1, 2, 1, 0, 0, 0, 0]))
