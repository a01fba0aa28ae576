"""The live pose message: joints placed from the root sensor down through each parent's rotation
(paper §3.4), so bones keep their length in every frame and a browser needs no math; and the
coaching names joints the way people do; an undetermined joint ends no bone.
"""

from __future__ import annotations

import numpy as np

from flockcal.names import joint_label, joint_name
from flockcal.server.pose import live_pose
from flockcal.simulator.performer import Performer


def test_pose_bones_keep_their_length_while_the_data_is_noisy():
    performer = Performer("human", "exercise", seed=3, rate_hz=100.0, noise="tracker")
    truth = performer.model.truth()
    names = list(performer.names)
    R, t, valid = performer.poses(np.array([1.0, 7.5, 13.0]))
    lengths = []
    for k in range(3):
        pose = live_pose(names, R[k], t[k], valid[k], truth)
        pts = np.array([j["p"] for j in pose["joints"]])
        lengths.append([np.linalg.norm(pts[a] - pts[b]) for a, b in pose["bones"]])
        root = next(j for j in pose["joints"] if j["kind"] == "root")
        np.testing.assert_allclose(root["p"], t[k, names.index(truth["root"])], atol=1e-5)
        assert len(pose["sensors"]) == len(names) and all(len(s["R"]) == 9 for s in pose["sensors"])
    # Same calibration, three different moments: every bone is as long as before (to the 10 µm rounding).
    np.testing.assert_allclose(lengths[0], lengths[1], atol=3e-5)
    np.testing.assert_allclose(lengths[0], lengths[2], atol=3e-5)
    assert max(lengths[0]) > 0.1


def test_pose_without_a_fit_shows_the_sensors_only():
    performer = Performer("human", "walk", seed=1, rate_hz=100.0)
    R, t, valid = performer.poses(np.array([0.5]))
    pose = live_pose(list(performer.names), R[0], t[0], valid[0], None)
    assert pose["joints"] == [] and pose["bones"] == [] and len(pose["sensors"]) == 16


def test_coaching_names_joints_as_people_do_whichever_body_the_tree_made_the_child():
    assert joint_label("l_forearm", "l_upper_arm") == "the left elbow"
    assert joint_label("r_shin", "r_thigh") == "the right knee"
    # A tree rooted at the arm names the shoulder by the chest: it is still the shoulder.
    assert joint_name("chest", "l_upper_arm") == joint_name("l_upper_arm", "chest") == "left shoulder"
    assert joint_name("pelvis", "abdomen") == joint_name("abdomen", "pelvis") == "lower back"
    assert joint_name("bird2", "bird1") == "bird 1–bird 2"
    assert joint_label("bird2", "bird1") == "the joint between the bird 1 and the bird 2"


def test_pose_draws_no_bone_to_an_undetermined_joint():
    performer = Performer("human", "exercise", seed=3, rate_hz=100.0, noise="tracker")
    truth = performer.model.truth()
    undetermined = "l_forearm"
    fit = dict(truth, joints=[dict(j, determined=j["child"] != undetermined) for j in truth["joints"]])
    names = list(performer.names)
    R, t, valid = performer.poses(np.array([2.0]))
    pose = live_pose(names, R[0], t[0], valid[0], fit)
    heads = [j["name"] for j in pose["joints"]]
    ends = {frozenset((heads[a], heads[b])) for a, b in pose["bones"]}
    # Neither the upper arm's bone to the elbow nor the forearm's on to the wrist; the elbow is still placed.
    assert frozenset(("l_upper_arm", "l_forearm")) not in ends and frozenset(("l_forearm", "l_hand")) not in ends
    assert frozenset(("r_upper_arm", "r_forearm")) in ends
    elbow = pose["joints"][heads.index(undetermined)]
    assert elbow["determined"] is False and elbow["p"] is not None
    full = live_pose(names, R[0], t[0], valid[0], truth)
    assert len(full["bones"]) == len(pose["bones"]) + 2


def test_the_live_calibration_draws_what_its_dict_draws():
    # The service draws the skeleton from the fit's typed Calibration; a stored result is a §5 dict. Both
    # must give the same message, undetermined joints included (a short take leaves some).
    from flockcal.solver.accumulator import GramAccumulator
    from flockcal.solver.solve import solve

    performer = Performer("human", "exercise", seed=3, rate_hz=100.0, noise="tracker")
    times = np.arange(600) / 100.0
    R, t, valid = performer.poses(times)
    acc = GramAccumulator(performer.n_sensors)
    acc.add_poses(R, t, valid)
    cal = solve(acc, list(performer.names))
    assert not all(cal.joints.determined) and any(cal.joints.determined)  # both kinds are drawn
    names = list(performer.names)
    assert live_pose(names, R[-1], t[-1], valid[-1], cal) == live_pose(names, R[-1], t[-1], valid[-1], cal.to_dict())
