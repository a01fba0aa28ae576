"""Promises of the pair fits: exact on exact data, equal to the paper's SVD solve, noise-aware hinges, stderrs."""

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from flockcal.solver.accumulator import GramAccumulator
from flockcal.solver.fits import all_pairs, joint_estimates, pair_fits
from reference import reference_pair_fit
from synthetic import articulated

MIXED = ["root", "ball", "hinge", "rigid", "ball", "hinge", "lowrange"]


def _fit(d, pairs=None):
    acc = GramAccumulator(d.n_sensors).add_poses(d.rotations, d.positions, d.valid)
    return pair_fits(acc, pairs)


def _reference(d, i, j):
    v = d.valid[:, i] & d.valid[:, j]
    return reference_pair_fit(d.rotations[:, i], d.positions[:, i], d.rotations[:, j], d.positions[:, j], valid=v)


def _rel(a, b):
    return np.linalg.norm(np.asarray(a) - np.asarray(b)) / max(np.linalg.norm(b), 1e-300)


def _assert_same_as_reference(f, k, ref):
    assert f.rank[k] == ref.rank
    assert _rel(f.c[k], ref.c) < 1e-9 and _rel(f.l[k], ref.l) < 1e-9
    assert np.allclose(f.singular_values[k][:ref.rank], ref.singular_values[:ref.rank], rtol=1e-9)
    if ref.rank == 5:
        assert f.hinge[k]
        assert np.allclose(f.axis_i[k], ref.axis_i, atol=1e-9) and np.allclose(f.axis_j[k], ref.axis_j, atol=1e-9)


def test_exact_data_gives_the_true_joint_centres_to_1e9_m():
    d = articulated(m=6, n=500, seed=5)
    f = _fit(d, d.joints)
    assert np.all(f.rank == 6) and not f.hinge.any()
    assert np.abs(f.c - d.c[d.joints[:, 0]]).max() < 1e-9
    assert np.abs(f.l - d.l[d.joints[:, 0]]).max() < 1e-9
    assert np.all(f.rms < 1e-6)


def test_gram_solve_equals_the_reference_svd_for_every_pair_including_hinges_and_rigid_pairs():
    d = articulated(m=7, n=400, seed=6, joint_types=MIXED)
    f = _fit(d)
    kinds = set()
    for k, (i, j) in enumerate(f.pairs):
        ref = _reference(d, i, j)  # the oracle decides its own rank from its own floor
        assert f.rank[k] == ref.rank, (i, j)
        kinds.add(int(f.rank[k]))
        if f.rms[k] < 1e-6:  # joints (and rigid pairs): the fit is exact, compare the solution itself
            _assert_same_as_reference(f, k, ref)
        assert abs(f.rms[k] - ref.rms) <= 1e-9 * max(ref.rms, 1.0) + f.rms_floor[k]
    assert {3, 5, 6} <= kinds  # rigid, hinge and ball pairs were all exercised


def test_hinge_gives_the_axis_in_both_frames_and_the_min_norm_point_on_it():
    d = articulated(m=3, n=400, seed=7, joint_types=["root", "hinge", "hinge"])
    f = _fit(d, d.joints)
    assert f.hinge.all() and np.all(f.rank == 5)
    for k, (i, j) in enumerate(d.joints):
        # Same axis (up to sign) as the truth, and the point lies on the true axis line in both frames.
        assert abs(abs(f.axis_i[k] @ d.axis_child[i]) - 1) < 1e-9 and abs(abs(f.axis_j[k] @ d.axis_parent[i]) - 1) < 1e-9
        off_c, off_l = f.c[k] - d.c[i], f.l[k] - d.l[i]
        assert np.linalg.norm(np.cross(off_c, d.axis_child[i])) < 1e-9
        assert abs(off_c @ d.axis_child[i] - off_l @ d.axis_parent[i]) < 1e-9  # slid the same amount in both
        # Min-norm: no component along the 6-D null vector (a_c, a_p).
        assert abs(f.c[k] @ f.axis_i[k] + f.l[k] @ f.axis_j[k]) < 1e-9


def test_pair_without_relative_rotation_drops_all_three_directions_without_nan():
    d = articulated(m=2, n=200, seed=8, joint_types=["root", "rigid"])
    f = _fit(d)
    assert f.rank[0] == 3 and not f.hinge[0] and not f.determined[0]
    assert np.isfinite(f.c).all() and np.isfinite(f.l).all()
    # Nothing turned: the point is the min-norm rule's, so no standard error is claimed for it.
    assert np.isinf(f.c_stderr).all() and np.isinf(f.direction_error).all()
    assert np.allclose(f.coverage[0], 0.0, atol=1e-12)
    _assert_same_as_reference(f, 0, _reference(d, 0, 1))


def test_single_frame_fits_without_nan():
    d = articulated(m=3, n=1, seed=9)
    f = _fit(d)
    assert np.all(f.rank == 3) and np.isfinite(f.c).all() and np.isfinite(f.rms).all()


def test_with_ten_percent_dropouts_fits_equal_the_reference_on_frames_where_both_are_valid():
    d = articulated(m=6, n=600, seed=10, joint_types=["root", "ball", "hinge", "ball", "ball", "ball"], dropout=0.1)
    f = _fit(d)
    for k, (i, j) in enumerate(f.pairs):
        ref = _reference(d, i, j)  # the oracle decides its own rank from its own floor
        assert f.n[k] == ref.n and f.rank[k] == ref.rank, (i, j)
        if f.rms[k] < 1e-6:
            _assert_same_as_reference(f, k, ref)
    joints = _fit(d, d.joints)
    ball = np.array([t == "ball" for t in d.joint_type])[d.joints[:, 0]]
    assert np.abs(joints.c[ball] - d.c[d.joints[ball, 0]]).max() < 1e-9


def test_low_range_ball_joint_keeps_its_full_3d_solution_under_tracker_noise():
    # A lumbar-like joint: wide flexion, only ±3° about the other axes, 10 cm levers, 0.5 mm / 0.1° noise.
    d = articulated(m=2, n=3000, seed=12, joint_types=["root", "lowrange"], amplitude=0.6, offset_scale=0.06,
                    position_noise=5e-4, rotation_noise=0.0017)
    f = _fit(d, d.joints)
    assert f.rank[0] == 6 and not f.hinge[0]
    assert f.coverage[0, 0] > 4 * f.rotation_noise[0] and f.determined[0]
    assert np.linalg.norm(f.c[0] - d.c[1]) < 5 * f.c_stderr[0] + 1e-3


def test_true_hinge_with_tracker_noise_is_a_hinge_and_its_centre_stays_on_the_axis_near_the_min_norm_point():
    d = articulated(m=2, n=3000, seed=13, joint_types=["root", "hinge"], offset_scale=0.1,
                    position_noise=5e-4, rotation_noise=0.0017)
    f = _fit(d, d.joints)
    assert f.hinge[0] and f.rank[0] == 5
    assert abs(abs(f.axis_i[0] @ d.axis_child[1]) - 1) < 1e-3
    # Within millimetres of the true axis line, and no farther along it than the exact min-norm point.
    off = f.c[0] - d.c[1]
    assert np.linalg.norm(np.cross(off, d.axis_child[1])) < 3e-3
    exact = articulated(m=2, n=3000, seed=13, joint_types=["root", "hinge"], offset_scale=0.1)
    fe = _fit(exact, exact.joints)
    assert np.linalg.norm(f.c[0] - fe.c[0]) < 1e-2 and np.linalg.norm(f.c[0]) < np.linalg.norm(fe.c[0]) + 1e-2


def test_standard_errors_match_the_scatter_of_repeated_noisy_fits():
    exact = articulated(m=2, n=300, seed=14)
    est, se = [], []
    for trial in range(12):  # same motion, fresh 2 mm position noise each time
        t = exact.positions + np.random.default_rng(100 + trial).normal(0, 2e-3, exact.positions.shape)
        f = pair_fits(GramAccumulator(2).add_poses(exact.rotations, t))
        est.append(f.c[0])
        se.append(f.c_stderr[0])
    scatter = np.sqrt(np.sum(np.var(np.array(est), axis=0, ddof=1)))
    assert 0.5 < np.mean(se) / scatter < 2.0


def test_fits_for_a_subset_of_pairs_equal_the_same_rows_of_all_pairs():
    d = articulated(m=5, n=300, seed=15)
    acc = GramAccumulator(5).add_poses(d.rotations, d.positions)
    whole = pair_fits(acc)
    some = pair_fits(acc, d.joints)  # (child, parent): the reverse of all_pairs' (low, high) order
    rows = [int(np.flatnonzero((whole.pairs == sorted(p)).all(axis=1))[0]) for p in d.joints]
    assert np.allclose(some.c, whole.l[rows]) and np.allclose(some.l, whole.c[rows])
    # Noise-free: both rms are zero to within the rounding level each fit states (~3e-7 m here), not
    # bitwise: a subset's Gram reduction may take another BLAS path.
    assert (np.abs(some.rms - whole.rms[rows]) <= some.rms_floor + whole.rms_floor[rows]).all()
    flipped = whole.take(rows, swap=np.ones(len(rows), bool))
    assert np.array_equal(flipped.pairs, d.joints) and np.allclose(flipped.c, some.c) and np.allclose(flipped.c_cov, some.c_cov)
    assert np.array_equal(all_pairs(5), whole.pairs)


@given(
    seed=st.integers(0, 10_000),
    m=st.integers(2, 6),
    kinds=st.lists(st.sampled_from(["ball", "hinge", "rigid", "lowrange"]), min_size=6, max_size=6),
    dropout=st.sampled_from([0.0, 0.1]),
)
def test_property_gram_fits_of_tree_joints_equal_the_reference_and_the_truth(seed, m, kinds, dropout):
    d = articulated(m=m, n=150, seed=seed, joint_types=["root"] + kinds[: m - 1], dropout=dropout)
    f = _fit(d, d.joints)
    for k, (i, j) in enumerate(d.joints):
        ref = _reference(d, i, j)
        _assert_same_as_reference(f, k, ref)
        if d.joint_type[i] in ("ball", "lowrange"):
            assert np.abs(f.c[k] - d.c[i]).max() < 1e-9
        assert f.rank[k] == {"ball": 6, "lowrange": 6, "hinge": 5, "rigid": 3}[d.joint_type[i]]


@given(st.integers(0, 2**16), st.sampled_from(["ball", "hinge"]), st.floats(0.0, 0.2))
def test_the_slip_loops_joint_estimates_are_the_full_fits_centres_bit_for_bit(seed, kind, dropout):
    # The slip loop refits with `joint_estimates` (no error bars); the slip figures were measured with
    # `pair_fits`' c and l, so they must be the same numbers, hinges (whose centre is re-solved) included.
    d = articulated(m=5, n=300, seed=seed, joint_types=kind, dropout=dropout, position_noise=1e-4,
                    rotation_noise=1e-3)
    acc = GramAccumulator(d.n_sensors).add_poses(d.rotations, d.positions, d.valid)
    pairs = all_pairs(d.n_sensors)[::-1]  # any order of pairs
    full = pair_fits(acc, pairs)
    lean = joint_estimates(acc, pairs)
    np.testing.assert_array_equal(lean.c, full.c)
    np.testing.assert_array_equal(lean.l, full.l)
