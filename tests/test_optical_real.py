"""`fit-markers` on the two real captures in ../shared/data, judged against their segment map.

Every expectation comes from segments.json (which marker sits on which segment, each segment's anatomical
parent) and from how far the technical clusters turned relative to each other (a measurement of the
capture, made here with the tests' own Kabsch, not by the code under test).
"""

from itertools import combinations

import numpy as np
import pytest

from plain_lsq import plain_fit
from real_captures import KNEE, UPPER_LIMB, capture_path, cluster_poses, cluster_take, marker_index, segment_map

# Segments whose technical clusters turned more than this relative to each other (90th percentile of the
# relative rotation's angle from its median) moved: soft tissue alone cannot turn a cluster by 30°.
MOVED_DEG = 30.0
# ...and less than this: they stayed still relative to each other (soft tissue turns a 3-marker cluster by
# a few degrees; the knee trial's idle segments stay within 3.0° of the pelvis, the right thigh turns 5.6°).
STILL_DEG = 4.0


def fit_capture(name: str):
    from flockcal.markers import load_c3d
    from flockcal.solver.optical.pipeline import fit_markers

    mt = load_c3d(capture_path(name))
    fit = fit_markers(mt.markers, mt.marker_names, mt.rate_hz, mt.times)
    return mt, fit, fit.to_dict()


def relative_turn_deg(take, a: str, b: str) -> float:
    """90th percentile of the angle between segment a's and b's relative rotation and its median."""
    from scipy.spatial.transform import Rotation

    i, j = take.names.index(a), take.names.index(b)
    ok = take.valid[:, i] & take.valid[:, j]
    rel = Rotation.from_matrix(np.einsum("nji,njk->nik", take.rotations[ok, j], take.rotations[ok, i]))
    mean = rel.mean()
    return float(np.degrees(np.percentile((mean.inv() * rel).magnitude(), 90)))


def body_of(fit, mt, name: str) -> str:
    k = marker_index(mt.marker_names, name)
    kept = fit.marker_names.index(mt.marker_names[k])
    for label, group in zip(fit.labels, fit.groups):
        if kept in group:
            return label
    raise AssertionError(f"marker {name} is in no body")


def segments_in(fit, mt, info, label: str) -> set[str]:
    return {seg for seg, names in info["segments"].items() for x in names if body_of(fit, mt, x) == label}


def tree_edges(out) -> set[frozenset]:
    return {frozenset(e) for e in out["parent"].items()}


@pytest.fixture(scope="module")
def knee():
    return fit_capture(KNEE)


@pytest.fixture(scope="module")
def upper_limb():
    return fit_capture(UPPER_LIMB)


@pytest.fixture(scope="module")
def knee_clusters():
    return cluster_take(KNEE)


def test_knee_trial_thigh_and_shank_clusters_each_in_one_body_with_no_moving_segment_mixed_in(knee, knee_clusters):
    mt, fit, _ = knee
    info = segment_map(KNEE)
    for seg in ("r_thigh", "r_shank"):
        bodies = {body_of(fit, mt, x) for x in info["technical_clusters"][seg]}
        assert len(bodies) == 1, f"{seg}'s technical cluster is split over {bodies}"
        body = bodies.pop()
        moved = {s for s in segments_in(fit, mt, info, body) - {seg}
                 if s in info["technical_clusters"] and relative_turn_deg(knee_clusters, seg, s) > MOVED_DEG}  # fmt: skip
        assert not moved, f"{seg}'s body {body} holds markers of {moved}, which turned > {MOVED_DEG}° against it"
    assert body_of(fit, mt, "RTHI1") != body_of(fit, mt, "RLEG1")


def test_knee_trial_segments_that_stayed_still_are_one_body_not_split(knee, knee_clusters):
    mt, fit, _ = knee
    info = segment_map(KNEE)
    still = [s for s in info["technical_clusters"] if s == "pelvis" or relative_turn_deg(knee_clusters, "pelvis", s) < STILL_DEG]
    assert len(still) >= 10  # the trial moves the right leg; trunk, head, arms and left leg hardly move
    bodies = {body_of(fit, mt, x) for s in still for x in info["segments"][s]}
    assert len(bodies) == 1, f"segments that stayed within {STILL_DEG}° of each other were split into {bodies}"


def test_knee_trial_tree_has_the_knee_and_no_unexercised_joint(knee, knee_clusters):
    mt, fit, out = knee
    thigh, shank = body_of(fit, mt, "RTHI1"), body_of(fit, mt, "RLEG1")
    assert tree_edges(out) == {frozenset([thigh, shank])}
    assert [sorted(j) for j in out["exercised_joints"]] == [sorted([thigh, shank])]
    still = body_of(fit, mt, "LASIS")
    assert still in out["unjoined"]  # the hip barely moved: no bone or edge from it
    assert not any(b["from_joint"] == still or b["to_joint"] == still for b in out["bones"])
    (joint,) = out["joints"]
    assert joint["determined"] is True


def reported_knee(fit, out) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The knee `fit-markers` reports, per frame in the world, its hinge axis there, and where both are known."""
    (joint,) = out["joints"]
    assert joint["hinge"]  # the knee trial swings the shank about one axis
    c = fit.labels.index(joint["child"])
    world = np.einsum("nij,j->ni", fit.rotations[:, c], np.array(joint["c"])) + fit.positions[:, c]
    axis = np.einsum("nij,j->ni", fit.rotations[:, c], np.array(joint["axis_child"]))
    return world, axis, fit.valid[:, c]


def lsq_knee(poses_i, poses_j) -> np.ndarray:
    """Plain least squares' joint of two (R, t, valid) pose series, per frame in the world (NaN where unseen)."""
    (Ri, ti, vi), (Rj, tj, vj) = poses_i, poses_j
    ref = plain_fit(Ri, ti, Rj, tj, vi & vj)
    world = np.einsum("nij,j->ni", Ri, ref.c) + ti
    world[~(vi & vj)] = np.nan
    return world


def across_axis(a: np.ndarray, b: np.ndarray, axis: np.ndarray) -> float:
    """Median over frames of |a − b| across the hinge axis: a hinge leaves the point along its axis to a rule
    (each method its own), so only the distance across it counts."""
    d = a - b
    d = d - np.einsum("ni,ni->n", d, axis)[:, None] * axis
    return float(np.nanmedian(np.linalg.norm(d, axis=1)))


def knee_offset(fit, out, take, thigh: str, shank: str) -> float:
    """Across the hinge axis, the knee `fit-markers` reports against plain least squares on the take's two
    sensors `thigh` and `shank` (the tests' own Kabsch poses)."""
    world, axis, seen = reported_knee(fit, out)
    i, j = take.names.index(thigh), take.names.index(shank)
    ref = lsq_knee(*((take.rotations[:, k], take.positions[:, k], take.valid[:, k] & seen) for k in (i, j)))
    return across_axis(world, ref, axis)


def test_knee_centre_near_plain_least_squares_on_the_same_markers(knee):
    # Claim (docs/optical.md, "Real captures"): the Kirk knee within 7 mm (measured 6.2 mm) of plain least
    # squares on the poses of the same two bodies' markers; margin 2 mm. Under soft tissue the
    # constant-distance point and the constant-offset point of two poses differ by millimetres.
    mt, fit, out = knee
    thigh, shank = body_of(fit, mt, "RTHI1"), body_of(fit, mt, "RLEG1")
    bodies = {b: [fit.marker_names[i] for i in fit.groups[fit.labels.index(b)]] for b in (thigh, shank)}
    take = cluster_take(KNEE, bodies)
    assert knee_offset(fit, out, take, thigh, shank) < 0.009


def test_knee_centre_near_plain_least_squares_on_the_whole_thigh_and_shank(knee):
    # Claim (docs/optical.md, "Real captures"): 4.8 mm from plain least squares on all six markers the
    # segment map puts on the thigh and all six on the shank; margin 1.2 mm.
    mt, fit, out = knee
    info = segment_map(KNEE)
    world, axis, seen = reported_knee(fit, out)
    ref = lsq_knee(cluster_poses(mt, info["segments"]["r_thigh"]), cluster_poses(mt, info["segments"]["r_shank"]))
    assert across_axis(world, ref, axis) < 0.006


def test_knee_centre_near_plain_least_squares_on_the_technical_clusters(knee, knee_clusters):
    # Claim (docs/optical.md, "Real captures"): against the technical clusters alone (RTHI1-3, RLEG1-3) the
    # knee is 10.5 mm off; margin 1.5 mm. Why not the 3 mm: the next test.
    _, fit, out = knee
    assert knee_offset(fit, out, knee_clusters, "r_thigh", "r_shank") < 0.012


def test_the_technical_clusters_put_the_knee_apart_from_where_the_legs_markers_put_it(knee):
    # Claim (docs/optical.md, "Real captures"): plain least squares on every choice of three thigh and three
    # shank markers (20 × 20) puts the knee, at their median, 11.0 mm from where the technical clusters alone
    # put it, and 4.9 mm from the reported knee: the 3 mm the issue asks for is below what the capture's own
    # markers agree on. Margins: the clusters' knee at least 3 mm off (the target itself), the reported one
    # within 6 mm and nearer than the clusters'.
    mt, fit, out = knee
    info = segment_map(KNEE)
    world, axis, seen = reported_knee(fit, out)
    thighs = {tri: cluster_poses(mt, tri) for tri in combinations(info["segments"]["r_thigh"], 3)}
    shanks = {tri: cluster_poses(mt, tri) for tri in combinations(info["segments"]["r_shank"], 3)}
    knees = {(a, b): lsq_knee(pa, pb) for a, pa in thighs.items() for b, pb in shanks.items()}
    consensus = np.nanmedian(np.stack(list(knees.values())), axis=0)
    technical = knees[tuple(info["technical_clusters"]["r_thigh"]), tuple(info["technical_clusters"]["r_shank"])]
    clusters_off, reported_off = across_axis(technical, consensus, axis), across_axis(world, consensus, axis)
    assert clusters_off > 0.003
    assert reported_off < min(0.006, clusters_off)


def test_upper_limb_box_pelvis_humerus_and_hand_each_one_body_of_their_own(upper_limb):
    mt, fit, _ = upper_limb
    info = segment_map(UPPER_LIMB)
    for seg in ("box", "pelvis", "humerus", "hand"):
        bodies = {body_of(fit, mt, x) for x in info["segments"][seg]}
        assert len(bodies) == 1, f"{seg} split over {bodies}"
        assert segments_in(fit, mt, info, bodies.pop()) == {seg}


def test_upper_limb_tree_follows_the_arm_in_anatomical_order_where_exercised(upper_limb):
    mt, fit, out = upper_limb
    info = segment_map(UPPER_LIMB)
    rank = {"thorax": 0, "clavicle": 0, "scapula": 0, "humerus": 1, "forearm": 2, "hand": 3}

    def chain_rank(label):
        ranks = {rank.get(s) for s in segments_in(fit, mt, info, label)}
        return ranks.pop() if len(ranks) == 1 else None

    for a, b in out["parent"].items():
        ra, rb = chain_rank(a), chain_rank(b)
        segs = segments_in(fit, mt, info, a) | segments_in(fit, mt, info, b)
        assert "box" not in segs, f"the box is joined ({a}–{b}); it is held, never a joint"
        assert "pelvis" not in segs or segs & {"thorax"}, f"the pelvis joined to {segs}"
        if ra is not None and rb is not None:
            assert abs(ra - rb) <= 1, f"{a}–{b} skips a segment of the arm"
    humerus, forearm, hand = (body_of(fit, mt, x) for x in ("ARMl", "STYLr", "INDEX"))
    # The elbow and the wrist turned far between their segments' markers: the trial exercised them.
    take = cluster_take(UPPER_LIMB)
    assert relative_turn_deg(take, "humerus", "forearm") > MOVED_DEG and relative_turn_deg(take, "forearm", "hand") > MOVED_DEG
    edges = tree_edges(out)
    assert frozenset([humerus, forearm]) in edges and frozenset([forearm, hand]) in edges
    # Issue 31: the humerus hangs from the scapula's markers (the acromion group), not the sternum's, once
    # the two clavicle markers that a joint moved against the thorax are a body of their own.
    assert "scapula" in segments_in(fit, mt, info, out["parent"][humerus]), out["parent"][humerus]
    assert body_of(fit, mt, "boite:gauche_ext") in out["unjoined"] and body_of(fit, mt, "ASISr") in out["unjoined"]
