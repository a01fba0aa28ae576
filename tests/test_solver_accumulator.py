"""Promises of the Gram accumulator: any batching gives the same sums, dropouts never poison, merge/forget work."""

import numpy as np
import pytest

from flockcal.solver.accumulator import GramAccumulator
from flockcal.solver.errors import SolverError
from synthetic import articulated


def _direct_gram(R, t, valid, origin):
    """Σ X_kᵀX_k straight from design.md §2, with invalid sensors' columns zeroed."""
    n, m = R.shape[:2]
    X = np.zeros((n, 3, 4 * m))
    for a in range(m):
        X[:, :, 3 * a:3 * a + 3] = R[:, a]
        X[:, :, 3 * m + a] = t[:, a] - origin
    X = np.where(np.repeat(np.concatenate([np.repeat(valid, 3, axis=1), valid], axis=1)[:, None, :], 3, axis=1), X, 0.0)
    return np.einsum("kri,krj->ij", X, X)


@pytest.fixture(scope="module")
def data():
    return articulated(m=5, n=700, seed=11, dropout=0.1)


def test_gram_is_the_sum_of_frame_blocks_in_the_documented_layout(data):
    acc = GramAccumulator(5).add_poses(data.rotations, data.positions, data.valid)
    want = _direct_gram(np.nan_to_num(data.rotations), np.nan_to_num(data.positions), data.valid, acc.origin)
    assert np.allclose(acc.gram, want, rtol=1e-12, atol=1e-9)
    assert acc.frames == 700
    assert np.array_equal(acc.pair_frames, (data.valid.T.astype(float) @ data.valid))


def test_one_frame_at_a_time_random_batches_and_merged_halves_give_the_same_gram(data):
    R, t, v = data.rotations, data.positions, data.valid
    whole = GramAccumulator(5).add_poses(R, t, v)
    single = GramAccumulator(5)
    for k in range(len(R)):
        single.add_poses(R[k], t[k], v[k])  # the (m, 3, 3) single-frame form
    rng = np.random.default_rng(0)
    batched = GramAccumulator(5)
    s = 0
    while s < len(R):
        e = s + int(rng.integers(1, 300))
        batched.add_poses(R[s:e], t[s:e], v[s:e])
        s = e
    first = GramAccumulator(5, origin=whole.origin).add_poses(R[:333], t[:333], v[:333])
    second = GramAccumulator(5, origin=whole.origin).add_poses(R[333:], t[333:], v[333:])
    merged = first + second
    for other in (single, batched, merged):
        assert np.allclose(other.gram, whole.gram, rtol=1e-12, atol=1e-10)
        A1, b1, d1, n1 = other.normal_equations([[0, 1], [3, 2]])
        A0, b0, d0, n0 = whole.normal_equations([[0, 1], [3, 2]])
        assert np.allclose(A1, A0, rtol=1e-12) and np.allclose(b1, b0, rtol=1e-10, atol=1e-10)
        assert np.allclose(d1, d0, rtol=1e-10) and np.array_equal(n1, n0)
        assert other.frames == whole.frames


def test_invalid_sensor_frames_holding_nan_do_not_poison_any_pair(data):
    acc = GramAccumulator(5).add_poses(data.rotations, data.positions, data.valid)
    assert np.isnan(data.positions).any()  # the generator really put NaN in the dropped sensor-frames
    assert np.isfinite(acc.gram).all()
    A, b, dd, n = acc.normal_equations(np.array([[i, j] for i in range(5) for j in range(5) if i != j]))
    assert np.isfinite(A).all() and np.isfinite(b).all() and np.isfinite(dd).all()


def test_nan_without_a_valid_mask_counts_as_invalid(data):
    with_mask = GramAccumulator(5).add_poses(data.rotations, data.positions, data.valid)
    without = GramAccumulator(5).add_poses(data.rotations, data.positions)
    assert np.allclose(without.gram, with_mask.gram, rtol=1e-12, atol=1e-10)
    assert np.array_equal(without.pair_frames, with_mask.pair_frames)


def test_forgetting_weights_each_frame_by_its_age_whatever_the_batching(data):
    lam = 0.99
    R, t, v = data.rotations[:300], data.positions[:300], data.valid[:300]
    batch = GramAccumulator(5, forgetting=lam).add_poses(R, t, v)
    single = GramAccumulator(5, forgetting=lam, origin=batch.origin)
    for k in range(300):
        single.add_poses(R[k:k + 1], t[k:k + 1], v[k:k + 1])
    assert np.allclose(single.gram, batch.gram, rtol=1e-10, atol=1e-12)
    # Frame k carries weight λ^(299−k): compare with the explicitly weighted direct sum.
    w = lam ** np.arange(299, -1, -1)
    want = _direct_gram(np.nan_to_num(R) * np.sqrt(w)[:, None, None, None], (np.nan_to_num(t) - batch.origin) * np.sqrt(w)[:, None, None], v, 0.0)
    assert np.allclose(batch.gram, want, rtol=1e-10, atol=1e-10)
    assert np.allclose(batch.pair_frames, (v.T * w) @ v)


def test_copy_is_a_snapshot_and_difference_of_snapshots_is_a_window(data):
    R, t, v = data.rotations, data.positions, data.valid
    acc = GramAccumulator(5).add_poses(R[:400], t[:400], v[:400])
    snap = acc.copy()
    acc.add_poses(R[400:], t[400:], v[400:])
    assert snap.frames == 400
    window = acc - snap
    direct = GramAccumulator(5, origin=acc.origin).add_poses(R[400:], t[400:], v[400:])
    assert np.allclose(window.gram, direct.gram, rtol=1e-9, atol=1e-8)
    assert np.array_equal(window.pair_frames, direct.pair_frames)


def test_merging_accumulators_with_different_origins_is_refused(data):
    # Tried: two workers that each picked their own first-frame origin.
    a = GramAccumulator(5).add_poses(data.rotations[:10], data.positions[:10])
    b = GramAccumulator(5).add_poses(data.rotations[500:510], data.positions[500:510])
    with pytest.raises(SolverError, match="origin"):
        a.merge(b)


@pytest.mark.parametrize(
    "shapes",
    [((4, 5, 3, 3), (4, 5, 2)), ((4, 6, 3, 3), (4, 6, 3)), ((4, 5, 3), (4, 5, 3))],
    ids=["positions not 3-vectors", "wrong sensor count", "rotations not 3x3"],
)
def test_wrong_shapes_are_refused_with_a_solver_error(shapes):
    # Tried: frames whose shapes do not match each other or the accumulator.
    acc = GramAccumulator(5)
    with pytest.raises(SolverError):
        acc.add_poses(np.zeros(shapes[0]), np.zeros(shapes[1]))


from hypothesis import given  # noqa: E402
from hypothesis import strategies as st  # noqa: E402


@given(
    seed=st.integers(0, 10_000),
    m=st.integers(2, 6),
    cuts=st.lists(st.integers(1, 399), max_size=6),
    worker_cut=st.integers(1, 399),
)
def test_property_any_batching_and_any_split_across_workers_give_the_same_normal_equations(seed, m, cuts, worker_cut):
    d = articulated(m=m, n=400, seed=seed, dropout=0.1)
    R, t, v = d.rotations, d.positions, d.valid
    whole = GramAccumulator(m).add_poses(R, t, v)
    pieces = GramAccumulator(m)
    edges = [0, *sorted(set(cuts)), 400]
    for s, e in zip(edges[:-1], edges[1:]):
        pieces.add_poses(R[s:e], t[s:e], v[s:e])
    a = GramAccumulator(m, origin=whole.origin).add_poses(R[:worker_cut], t[:worker_cut], v[:worker_cut])
    b = GramAccumulator(m, origin=whole.origin).add_poses(R[worker_cut:], t[worker_cut:], v[worker_cut:])
    pairs = np.array([[i, j] for i in range(m) for j in range(m) if i != j])
    want = whole.normal_equations(pairs)
    for acc in (pieces, a.merge(b)):
        got = acc.normal_equations(pairs)
        for x, y in zip(got, want):
            assert np.allclose(x, y, rtol=1e-11, atol=1e-9)
