"""Issue 31 on the simulator: the walk and kiosk routines with skin markers under soft tissue, through
`fit_markers` — every body found, every marker on its own body, the true tree, the swap found, bones
within docs/optical.md's figures (3–4 markers a body; see there for 2–4, which does not meet them)."""

import numpy as np
import pytest

from flockcal.simulator import optical as so
from flockcal.solver.optical.pipeline import fit_markers


def bone_key(b, parent):
    """A bone is the pair of joints it spans, each joint the pair of bodies it links (root-independent)."""
    f, t = b["from_joint"], b["to_joint"]
    return frozenset([frozenset([f, parent[f]]), frozenset([t, parent[t]])])


@pytest.fixture(scope="module", params=["walk", "kiosk"])
def soft_fit(request):
    # docs/optical.md's conditions: 30 s at 144 Hz, 1 mm noise, 3.6 % gaps, one label swap, 8 mm of soft
    # tissue (each marker sliding over its bone with the joints' angles), seed 1.
    take, truth = so.simulate_markers("human", request.param, seconds=30, rate_hz=144, seed=1, per_body=(3, 4),
                                      noise_m=0.001, occlusion=0.036, n_swaps=1, sta_mm=8.0)
    out = fit_markers(take.markers, take.marker_names, take.rate_hz, take.times).to_dict()
    return request.param, take, truth, out


def test_every_body_found_and_every_marker_on_its_own(soft_fit):
    _, _, truth, out = soft_fit
    assert len(out["bodies"]) == len(set(truth["marker_body"].values()))
    for label, markers in out["bodies"].items():
        assert {truth["marker_body"][m] for m in markers} == {label}, (label, markers)


def test_the_tree_is_the_true_tree(soft_fit):
    # On the previous code (tree costs from Kirk's residual) the walk's tree had 3 wrong edges of 15; without
    # soft tissue it hung the head from the right forearm: Kirk's free per-frame point fits any two bodies
    # to a few millimetres, the pair fit leaves centimetres where no joint is.
    _, _, truth, out = soft_fit
    assert {frozenset(e) for e in out["parent"].items()} == {frozenset(e) for e in truth["parent"].items()}


def test_the_label_swap_is_found(soft_fit):
    _, take, truth, out = soft_fit
    (start, stop, a, b), = truth["swaps"]
    t0, t1 = take.times[start], take.times[stop - 1]
    assert any(set(e["markers"]) == {a, b} and e["time_s"] <= t1 and e["stop_s"] >= t0 for e in out["swap_events"])


def test_bones_within_the_documented_figures(soft_fit):
    # docs/optical.md: median within 5.5 mm, worst within 20 mm (measured 3.7 / 18.6 walk, 5.2 / 11.3 kiosk);
    # margins 1 mm and 5 mm. The previous code (Kirk's per-frame points) gave a median of 6.9 mm on the walk.
    _, _, truth, out = soft_fit
    true = {bone_key(b, truth["parent"]): b["length_m"] for b in truth["bones"]}
    errs = np.abs([b["length_m"] - true[bone_key(b, out["parent"])] for b in out["bones"]
                   if bone_key(b, out["parent"]) in true])
    assert len(errs) == len(true)
    assert np.median(errs) <= 0.0055 + 0.001
    assert errs.max() <= 0.020 + 0.005


def test_joints_between_posed_bodies_are_placed_by_the_pair_fit(soft_fit):
    # The JSON says which route placed each joint; with 3-4 markers every body has a pose, so most joints
    # are pinned well enough by the poses (the trunk's short-range joints may not be).
    _, _, truth, out = soft_fit
    placed = {frozenset(j) for j in out["pair_fit_joints"]}
    tree = {frozenset(e) for e in out["parent"].items()}
    assert placed <= tree and len(placed) >= len(tree) // 2


@pytest.fixture(scope="module", params=["walk", "kiosk"])
def two_marker_fit(request):
    # The issue's own case: 2-4 markers a body (seven bodies of two markers at seed 0), the same conditions.
    take, truth = so.simulate_markers("human", request.param, seconds=30, rate_hz=144, seed=0, per_body=(2, 4),
                                      noise_m=0.001, occlusion=0.036, n_swaps=1, sta_mm=8.0)
    return truth, fit_markers(take.markers, take.marker_names, take.rate_hz, take.times).to_dict()


def test_two_marker_bodies_are_found_and_joined_by_their_point_joints(two_marker_fit):
    # docs/optical.md, issue 31 table (2-4 markers, seed 0): every body and every marker (walk and kiosk
    # 16/16, 1.000), 12 of 15 true edges, 1 wrong on the walk and none on the kiosk. Before (Kirk's fit
    # judging every joint to a body of two markers): 15/16 bodies on the walk, 11/15 and 12/15 edges with 3
    # wrong each. Margins: one edge either way.
    truth, out = two_marker_fit
    assert len(out["bodies"]) == len(set(truth["marker_body"].values()))
    for label, markers in out["bodies"].items():
        assert {truth["marker_body"][m] for m in markers} == {label}, (label, markers)
    found, true = ({frozenset(e) for e in p.items()} for p in (out["parent"], truth["parent"]))
    assert len(found & true) >= 11
    assert len(found - true) <= 2
    two = {b for b, ms in out["bodies"].items() if len(ms) == 2}
    assert out["point_joints"] and all(set(j) & two for j in out["point_joints"])


def segmented(routine, seed):
    """Bodies (sets of true body names, one per found body) and the truth of a 2-4-marker take of the
    issue's conditions, from the segmentation alone."""
    from flockcal.solver.optical.segmentation import segment_markers

    take, truth = so.simulate_markers("human", routine, seconds=30, rate_hz=144, seed=seed, per_body=(2, 4),
                                      noise_m=0.001, occlusion=0.036, n_swaps=1, sta_mm=8.0)
    seg = segment_markers(take.markers)
    names = take.marker_names
    return [[truth["marker_body"][names[i]] for i in g] for g in seg.groups], truth


def test_a_trunk_segment_of_two_markers_stays_off_the_body_beyond_its_joint():
    # docs/optical.md, issue 31 ("a joint elsewhere"): the kiosk seed 8's pelvis of two markers moved within
    # the 15 mm tolerance of the head, so the size put it there (15/16 bodies before); the abdomen pins the
    # pelvis pair's joint within 5 mm (1.9 mm rms) and the head's markers' distances to that point vary by
    # 11.3 mm rms, over the 10 mm. Now every body and every marker on its own.
    bodies, truth = segmented("kiosk", 8)
    assert len(bodies) == len(set(truth["marker_body"].values()))
    assert all(len(set(b)) == 1 for b in bodies), [b for b in bodies if len(set(b)) > 1]


def test_two_markers_of_one_segment_slid_apart_are_one_body_by_their_joint():
    # docs/optical.md, issue 31 ("a lone pair"): the walk seed 3's right upper arm, its two markers'
    # distance ranging over 15.1 mm (over the tolerance) so each was left a body of its own before; the
    # chest pins the shoulder to them as a unit (2.0 mm, 3.5 mm rms). Now one body of exactly those two.
    bodies, truth = segmented("walk", 3)
    arm = [b for b in bodies if "r_upper_arm" in b]
    assert arm == [["r_upper_arm", "r_upper_arm"]]
