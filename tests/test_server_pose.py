"""The live pose message: joints placed from the root sensor down through each parent's rotation
(paper §3.4), so bones keep their length in every frame and a browser needs no math; and the
coaching sentences name joints the way people do.
"""

from __future__ import annotations

import numpy as np

from flockcal.server.coaching import hints, joint_label, progress
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


def test_coaching_names_joints_readably_and_asks_for_movement_where_coverage_is_low():
    assert joint_label("l_forearm", "l_upper_arm") == "the left elbow"
    assert joint_label("r_shin", "r_thigh") == "the right knee"
    fit = {"joints": [
        {"child": "l_forearm", "parent": "l_upper_arm", "hinge": False, "coverage": [0.0, 0.0, 0.001],
         "c_stderr_m": 0.05, "l_stderr_m": 0.05},
        {"child": "r_shin", "parent": "r_thigh", "hinge": True, "coverage": [0.4, 0.01, 0.0],
         "c_stderr_m": 0.001, "l_stderr_m": 0.001},
    ]}
    out = hints(fit)
    assert [h["joint"] for h in out] == ["l_forearm"]  # the knee is a hinge that has moved enough
    assert "left elbow" in out[0]["hint"] and out[0]["hint"].startswith("Move")
    assert progress(fit) == 0.5
