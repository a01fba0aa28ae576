"""The optical pipeline end to end: simulated markers → bodies, tree, bone lengths, poses, swaps, JSON."""

import numpy as np
import pytest

from flockcal.simulator import optical as so
from flockcal.solver.optical.pipeline import OpticalError, body_labels, fit_markers


def edge_set(parent_map):
    return {frozenset(e) for e in parent_map.items()}


def bone_key(b, parent):
    """A bone is the pair of joints it spans, each joint the pair of bodies it links (root-independent)."""
    f, t = b["from_joint"], b["to_joint"]
    return frozenset([frozenset([f, parent[f]]), frozenset([t, parent[t]])])


def bone_errors(out, truth):
    true = {bone_key(b, truth["parent"]): b["length_m"] for b in truth["bones"]}
    errs = [b["length_m"] - true[bone_key(b, out["parent"])] for b in out["bones"] if bone_key(b, out["parent"]) in true]
    return np.abs(errs), len(true)


@pytest.fixture(scope="module")
def human_fit():
    # 2–4 markers per body, 1 mm noise, 3 % occlusion gaps
    take, truth = so.simulate_markers("human", seconds=12, rate_hz=60, seed=2, noise_m=0.001, occlusion=0.03)
    fit = fit_markers(take.markers, take.marker_names, take.rate_hz, take.times)
    return take, truth, fit, fit.to_dict()


@pytest.fixture(scope="module")
def swapped_fit():
    # 3–4 markers per body (a swap between two 2-marker bodies is a documented limit), two label swaps
    take, truth = so.simulate_markers(
        "human", seconds=12, rate_hz=60, seed=2, noise_m=0.001, occlusion=0.02, n_swaps=2, per_body=(3, 4)
    )
    fit = fit_markers(take.markers, take.marker_names, take.rate_hz, take.times)
    return take, truth, fit, fit.to_dict()


def test_bodies_are_recovered_and_named_after_their_markers(human_fit):
    take, truth, fit, out = human_fit
    assert set(out["bodies"]) == set(truth["sensors"])
    for label, markers in out["bodies"].items():
        assert {truth["marker_body"][m] for m in markers} == {label}


def test_topology_has_only_true_edges(human_fit):
    # 2-4 markers a body: a joint to a body of two markers is a tree edge only when a point fixed in its
    # posed neighbour's frame is pinned within the sensor path's 5 mm (docs/optical.md); one pinned worse
    # leaves a forest rather than a wrong edge. Measured 14 of 15 true edges, none wrong (the pelvis of two
    # markers to the left thigh is pinned to 5.2 mm); margin 1 edge. Before, Kirk's fit judged these joints
    # and this take's tree was right, while the simulated walks under soft tissue had 3-4 wrong edges.
    _, truth, _, out = human_fit
    found, true = edge_set(out["parent"]), edge_set(truth["parent"])
    assert found <= true
    assert len(found) >= len(true) - 2


def test_bone_lengths_within_a_few_mm_at_1mm_marker_noise(human_fit):
    _, truth, _, out = human_fit
    errs, n_true = bone_errors(out, truth)
    assert len(errs) >= n_true - 6  # the bones between the forest's found joints (measured 10 of 15)
    assert np.median(errs) < 0.003
    assert errs.max() < 0.008


def test_marker_swaps_are_found_and_named(swapped_fit):
    take, truth, _, out = swapped_fit
    assert truth["swaps"]
    for start, stop, a, b in truth["swaps"]:
        t0, t1 = take.times[start], take.times[stop - 1]
        hits = [e for e in out["swap_events"] if set(e["markers"]) == {a, b} and e["time_s"] <= t1 and e["stop_s"] >= t0]
        assert hits, f"swap {a}↔{b} at {t0:.2f}–{t1:.2f}s not reported: {out['swap_events']}"


def test_bone_lengths_stay_within_a_few_mm_despite_swaps(swapped_fit):
    _, truth, _, out = swapped_fit
    assert edge_set(out["parent"]) == edge_set(truth["parent"])
    errs, _ = bone_errors(out, truth)
    assert np.median(errs) < 0.003
    assert errs.max() < 0.015  # measured 10 mm worst (a short-range trunk joint); README lists it


def test_json_has_the_fit_contract_shape_plus_bodies(human_fit):
    _, _, fit, out = human_fit
    for key in ("sensors", "root", "parent", "frames", "joints", "bones", "loop_candidates", "slip_events", "bodies"):
        assert key in out
    j = out["joints"][0]
    for key in ("child", "parent", "c", "l", "rms_m", "epsilon", "singular_values", "hinge", "axis_child",
                "axis_parent", "coverage", "c_stderr_m", "l_stderr_m"):  # fmt: skip
        assert key in j
    assert len(j["singular_values"]) == 6 and len(j["coverage"]) == 3
    assert out["sensors"] == list(fit.labels)
    assert out["root"] not in out["parent"] and len(out["parent"]) <= len(out["sensors"]) - 1
    assert set(out["parent"]) | set(out["parent"].values()) | set(out["unjoined"]) | {out["root"]} == set(out["sensors"])


def test_derived_poses_go_through_the_magnetic_solver_and_agree(human_fit):
    from flockcal.solver.accumulator import GramAccumulator
    from flockcal.solver.fits import pair_fits

    _, _, fit, out = human_fit
    take = fit.take()
    acc = GramAccumulator(take.n_sensors)
    acc.add_poses(take.rotations, take.positions, take.valid)
    idx = {n: i for i, n in enumerate(take.names)}
    pairs = np.array([[idx[j["child"]], idx[j["parent"]]] for j in out["joints"]])
    pf = pair_fits(acc, pairs)
    kirk = np.array([j["c"] for j in out["joints"]])
    assert np.median(np.linalg.norm(pf.c - kirk, axis=1)) < 0.003
    assert np.median(pf.rms) < 0.005


def test_three_rods_with_universal_joints_middle_rod_within_1cm():
    model = so.rods((0.45, 0.50, 0.45), seed=7)
    take, truth = so.simulate_markers(model, so.rod_motion(model, 15, 60, 7), per_body=(2, 3), noise_m=0.001, seed=7)
    out = fit_markers(take.markers, take.marker_names, take.rate_hz).to_dict()
    assert edge_set(out["parent"]) == edge_set(truth["parent"])
    middle = [b for b in out["bones"] if "rod1" in b["body"]]
    assert len(middle) == 1
    assert abs(middle[0]["length_m"] - 0.50) < 0.01


def test_one_marker_bodies_are_named_by_number_and_prefixes_used_otherwise():
    names = ("LKNE", "lthigh_1", "lthigh_2", "RKNE")
    groups = [np.array([0]), np.array([1, 2]), np.array([3])]
    assert body_labels(names, groups) == ("body0", "lthigh", "body2")


def test_markers_that_all_move_together_are_refused():
    # tried: four markers on one rigid body — no joint exists
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(4, 3)) * 0.1
    from flockcal.rotations import random_rotations

    R = random_rotations(rng, (200,))
    M = np.einsum("nij,kj->nki", R, pts) + rng.normal(size=(200, 1, 3))
    with pytest.raises(OpticalError, match="one rigid body"):
        fit_markers(M, ["a", "b", "c", "d"], 60.0)
