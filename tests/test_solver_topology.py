"""Promises of the topology search: the right tree, root choice, rigid groups, loop candidates and ties."""

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from flockcal.solver.accumulator import GramAccumulator
from flockcal.solver.fits import pair_fits
from flockcal.solver.topology import spanning_tree, tree_centre
from synthetic import articulated


def _topology(d, root=None):
    acc = GramAccumulator(d.n_sensors).add_poses(d.rotations, d.positions, d.valid)
    return spanning_tree(pair_fits(acc), d.n_sensors, root)


def _bodies(topo, parent):
    """Undirected edges between rigid bodies, for comparing trees that differ only inside a rigid group."""
    lab = topo.group
    return {frozenset((int(lab[i]), int(lab[p]))) for i, p in enumerate(parent) if p >= 0 and lab[i] != lab[p]}


def test_exact_data_gives_the_true_tree_with_strictly_positive_weights_for_perfect_fits():
    d = articulated(m=10, n=400, seed=21)  # every joint fits to ~1e-9 m: zero weights would lose edges
    topo = _topology(d, root=0)
    assert np.array_equal(topo.parent, d.parent)
    assert topo.order[0] == 0 and all(np.flatnonzero(topo.order == p)[0] < np.flatnonzero(topo.order == i)[0]
                                      for i, p in enumerate(topo.parent) if p >= 0)
    assert not topo.rigid_groups and not topo.loop_candidates and not topo.ambiguous


def test_automatic_root_is_the_body_that_splits_the_tree_most_evenly():
    chain = np.array([-1, 0, 1, 2, 3, 4, 5])  # a chain of 7: the middle body
    d = articulated(m=7, n=300, seed=22, parent=chain)
    assert _topology(d).root == 3
    star = np.array([[0, 1], [0, 2], [0, 3], [3, 4]])
    assert tree_centre(star, 5) == 0


def test_sensors_that_never_turn_relative_to_each_other_form_one_rigid_group_not_a_joint():
    d = articulated(m=5, n=400, seed=23, joint_types=["root", "ball", "rigid", "ball", "ball"], parent=[-1, 0, 1, 1, 0])
    topo = _topology(d, root=0)
    assert topo.rigid_groups == [[1, 2]]
    # Either member may carry the body's joint to 0 (both fit it exactly); the other hangs rigidly from it.
    entry, member = (1, 2) if topo.joint[1] else (2, 1)
    assert topo.joint[entry] and topo.parent[entry] == 0
    assert not topo.joint[member] and topo.parent[member] == entry
    assert _bodies(topo, topo.parent) == _bodies(topo, d.parent)


def test_coincident_joint_centres_are_reported_as_ambiguous_and_as_a_loop_candidate():
    # Bodies 1 and 2 both hinge on the same point of body 0: 1–2 also has a fixed point.
    base = articulated(m=3, n=400, seed=24, parent=[-1, 0, 0])
    d = articulated(m=3, n=400, seed=24, parent=[-1, 0, 0], l_override={2: base.l[1]})
    topo = _topology(d, root=0)
    assert topo.ambiguous, "a tie between two parents must be reported"
    child, parents, note = topo.ambiguous[0]
    assert len(parents) == 2 and "coincident" in note
    tree = {frozenset((i, int(p))) for i, p in enumerate(topo.parent) if p >= 0}
    outside = {frozenset(p) for p in ((0, 1), (0, 2), (1, 2))} - tree
    assert [frozenset(lc[:2]) for lc in topo.loop_candidates] == list(outside)


def test_noisy_data_still_gives_the_true_tree():
    d = articulated(m=8, n=1500, seed=25, position_noise=1e-3, rotation_noise=0.003, dropout=0.05)
    topo = _topology(d, root=0)
    assert np.array_equal(topo.parent, d.parent)
    assert not topo.ambiguous


@given(seed=st.integers(0, 10_000), m=st.integers(2, 9), dropout=st.sampled_from([0.0, 0.1]))
def test_property_random_skeletons_in_random_motion_give_their_own_tree(seed, m, dropout):
    d = articulated(m=m, n=200, seed=seed, dropout=dropout)
    topo = _topology(d, root=0)
    assert np.array_equal(topo.parent, d.parent)


@given(st.integers(1, 24), st.floats(0.0, 0.3), st.integers(0, 2**16))
def test_rigid_bodies_are_csgraphs_connected_components(m, density, seed):
    # `rigid_bodies` searches the components in Python instead of csgraph (importing scipy.sparse cost every
    # `flockcal fit` ~0.05 s): the same count and the same labels, numbered by each component's lowest
    # sensor, on any "never turned" matrix (not symmetric: either direction links two sensors).
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import connected_components

    from flockcal.solver.topology import rigid_bodies

    rigid = np.random.default_rng(seed).random((m, m)) < density
    n, label = rigid_bodies(rigid.tobytes(), m)
    n_want, label_want = connected_components(csr_matrix(rigid), directed=False)
    assert n == n_want
    np.testing.assert_array_equal(label, label_want)


@given(st.integers(1, 16), st.floats(0.2, 1.0), st.integers(0, 2**16))
def test_the_tree_links_are_csgraphs_minimum_spanning_forest(n, density, seed):
    # `_tree_links` runs Kruskal's in Python instead of csgraph (a fifth of a live refit went into its
    # sparse set-up); on distinct rank weights the forest is unique, so csgraph's must be the same.
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import minimum_spanning_tree

    from flockcal.solver.topology import _tree_links

    rng = np.random.default_rng(seed)
    upper = np.array([(i, j) for i in range(n) for j in range(i + 1, n)], dtype=np.intp).reshape(-1, 2)
    links = upper[rng.random(len(upper)) < density]
    if not len(links):
        return
    a, b = links[:, 0].copy(), links[:, 1].copy()
    w = np.empty(len(links))
    w[rng.permutation(len(links))] = np.arange(1, len(links) + 1)
    mst = minimum_spanning_tree(csr_matrix((w, (a, b)), shape=(n, n))).toarray()
    expected = (mst[a, b] > 0) | (mst[b, a] > 0)
    np.testing.assert_array_equal(_tree_links(n, a.tobytes(), b.tobytes(), w.tobytes()), expected)
