"""Promises of the simulated bodies (issue 3, part 1): proportions, joints, sensors and ground truth."""

import numpy as np
import pytest

from flockcal.simulator import body, motion
from flockcal.simulator.body import SimulatorError


def _joint_world(model, mo):
    """World position of every joint by forward kinematics, and both sensors' views of it from truth."""
    R, t = body.sensor_poses(model, mo)
    J = body.joint_positions(model, mo.local_rotations, mo.root_translation)
    out = []
    for j in model.truth()["joints"]:
        i, p = model.index(j["child"]), model.index(j["parent"])
        from_child = np.einsum("nij,j->ni", R[:, i], j["c"]) + t[:, i]
        from_parent = np.einsum("nij,j->ni", R[:, p], j["l"]) + t[:, p]
        out.append((J[:, i], from_child, from_parent))
    return out


@pytest.mark.parametrize("make", [lambda: body.human(seed=3), lambda: body.human(n_bodies=15, seed=4), body.linkage, body.rigid_pair])
def test_truth_c_and_l_reproduce_every_joint_exactly(make):
    model = make()
    mo = motion.routine(model, "walk", seconds=3, rate_hz=50, seed=2)
    for joint, from_child, from_parent in _joint_world(model, mo):
        assert np.abs(from_child - joint).max() < 1e-12
        assert np.abs(from_parent - joint).max() < 1e-12


def test_human_has_sixteen_named_bodies_rooted_at_the_pelvis_with_hinged_knees_and_elbows():
    model = body.human()
    assert model.m == 16
    assert model.names[model.root] == "pelvis"
    for n in ("chest", "head", "l_upper_arm", "l_forearm", "l_hand", "r_hand", "l_thigh", "l_shin", "l_foot", "r_foot"):
        assert n in model.names
    types = dict(zip(model.names, model.joint_type))
    assert {n for n, t in types.items() if t == "hinge"} == {"l_forearm", "r_forearm", "l_shin", "r_shin"}
    assert all(types[n] == "ball" for n in ("l_upper_arm", "l_hand", "l_thigh", "l_foot", "head"))
    hinge = np.array([t == "hinge" for t in model.joint_type])
    assert np.allclose(np.linalg.norm(model.hinge_axis[hinge], axis=1), 1.0)
    # Hinges rotate about the left-right axis, give or take a few degrees of per-subject tilt.
    assert np.all(np.abs(model.hinge_axis[hinge, 1]) > np.cos(np.radians(10)))


def test_sensor_sits_on_the_skin_a_few_centimetres_from_the_bone():
    model = body.human()
    for n in ("l_upper_arm", "l_forearm", "l_thigh", "r_shin"):
        i = model.index(n)
        s = model.sensor_offset[i]
        radial = np.linalg.norm(s[:2])  # limbs run along the bone frame's z
        assert 0.01 < radial < 0.12
        assert 0.0 < s[2] < np.linalg.norm(model.joint_offset[model.children(i)[0]])
    assert np.allclose(model.sensor_rotation @ model.sensor_rotation.transpose(0, 2, 1), np.eye(3), atol=1e-12)
    assert np.allclose(np.linalg.det(model.sensor_rotation), 1.0)


def test_proportions_follow_height_and_vary_per_subject():
    tall, short = body.human(height=1.9, variation=0.0), body.human(height=1.5, variation=0.0)
    assert np.allclose(tall.joint_offset * 1.5, short.joint_offset * 1.9)
    thigh = {s: np.linalg.norm(body.human(seed=s).joint_offset[body.human().index("l_shin")]) for s in range(6)}
    assert len({round(v, 6) for v in thigh.values()}) == 6
    assert all(0.35 < v < 0.55 for v in thigh.values())  # a 1.75 m person's thigh, ± a few percent
    assert np.array_equal(body.human(seed=2).sensor_offset, body.human(seed=2).sensor_offset)


def test_truth_has_the_fit_json_shape_and_bone_definition():
    model = body.human()
    truth = model.truth()
    assert truth["root"] == "pelvis"
    assert truth["parent"]["l_hand"] == "l_forearm" and "pelvis" not in truth["parent"]
    assert len(truth["joints"]) == 15
    for j in truth["joints"]:
        assert {"child", "parent", "c", "l", "hinge", "axis_child", "axis_parent"} <= set(j)
        assert (j["axis_child"] is not None) == j["hinge"]
    bones = {(b["body"], b["from_joint"], b["to_joint"]): b["length_m"] for b in truth["bones"]}
    # A non-root body: inboard joint (named by the body itself) to each outboard joint.
    upper = np.linalg.norm(model.joint_offset[model.index("l_forearm")])
    assert bones[("l_upper_arm", "l_upper_arm", "l_forearm")] == pytest.approx(upper)
    # The root: between pairs of its outboard joints (hip to hip).
    hips = model.joint_offset[model.index("l_thigh")] - model.joint_offset[model.index("r_thigh")]
    assert bones[("pelvis", "l_thigh", "r_thigh")] == pytest.approx(np.linalg.norm(hips))
    # Never a sensor-to-joint distance: every bone joins two joint names of the parent map.
    joints = set(truth["parent"])
    assert all(b["from_joint"] in joints and b["to_joint"] in joints for b in truth["bones"])


@pytest.mark.parametrize("n", range(2, 17))
def test_fewer_birds_keep_a_connected_tree_of_real_joints(n):
    model = body.human(n_bodies=n)
    assert model.m == n
    assert (model.parent >= 0).sum() == n - 1
    if n < 16:
        assert "abdomen" not in model.names  # the chest then hangs straight from the pelvis
    if n == 6:
        assert model.names == ("pelvis", "chest", "head", "l_upper_arm", "l_forearm", "l_hand")


def test_fifteen_body_human_merges_the_abdomen_into_the_pelvis():
    full, merged = body.human(seed=5), body.human(seed=5, n_bodies=15)
    # The chest's joint stays where it was: at the thoracolumbar junction, now in the pelvis frame.
    expected = full.joint_offset[full.index("abdomen")] + full.joint_offset[full.index("chest")]
    assert np.allclose(merged.joint_offset[merged.index("chest")], expected)
    assert merged.names[merged.parent[merged.index("chest")]] == "pelvis"


def test_linkage_is_a_chain_of_five_ball_joints_with_known_spacing():
    lengths = (0.2, 0.25, 0.3, 0.25, 0.2, 0.15)
    model = body.linkage(lengths)
    assert model.m == 6 and model.joint_type[1:] == ("ball",) * 5
    assert list(model.parent) == [-1, 0, 1, 2, 3, 4]
    bones = {b["body"]: b["length_m"] for b in model.truth()["bones"] if b["body"] != "link0"}
    assert [bones[f"link{k}"] for k in range(1, 5)] == pytest.approx(lengths[1:5])


def test_rigid_pair_holds_its_sensors_the_known_distance_apart():
    model = body.rigid_pair(0.565)
    mo = motion.routine(model, "walk", seconds=5, rate_hz=20, seed=1)
    R, t = body.sensor_poses(model, mo)
    assert np.allclose(np.linalg.norm(t[:, 1] - t[:, 0], axis=1), 0.565, atol=1e-12)
    assert np.ptp(t[:, 0], axis=0).max() > 0.05  # it is carried about, not parked
    assert model.truth()["sensor_distance_m"] == 0.565


@pytest.mark.parametrize(
    "call",
    [
        lambda: body.human(height=17.5),  # centimetres/decimetres instead of metres
        lambda: body.human(n_bodies=17),  # more bodies than the suit has
        lambda: body.human(variation=-0.1),  # negative spread
        lambda: body.linkage((0.2, 0.3)),  # too few links
        lambda: body.rigid_pair(0.0),  # sensors on top of each other
        lambda: body.human().subset(["pelvis", "l_forearm"]),  # a forearm without its upper arm
        lambda: body.by_name("octopus"),  # an unknown model
    ],
)
def test_bad_body_requests_raise_a_simulator_error(call):
    with pytest.raises(SimulatorError):
        call()
