"""Rigid-body clustering of optical markers (Kirk et al. 2005 §2) on the simulator's optical mode."""

import numpy as np
import pytest

from flockcal.simulator import optical as so
from flockcal.solver.optical.clustering import (
    ClusteringError,
    cluster_markers,
    distance_std,
    jittered_frames,
)


def same_partition(labels, truth_body) -> bool:
    a = {tuple(np.flatnonzero(labels == g)) for g in np.unique(labels)}
    b = {tuple(np.flatnonzero(truth_body == g)) for g in np.unique(truth_body)}
    return a == b


def truth_bodies(take, truth):
    names = [truth["marker_body"][m] for m in take.marker_names]
    return np.unique(names, return_inverse=True)[1]


@pytest.fixture(scope="module")
def human_take():
    return so.simulate_markers("human", seconds=8, rate_hz=60, seed=3, noise_m=0.001, occlusion=0.03)


def test_clustering_recovers_every_body_of_a_noisy_occluded_human(human_take):
    take, truth = human_take
    cl = cluster_markers(take.markers)
    assert cl.n_groups == 16
    assert same_partition(cl.labels, truth_bodies(take, truth))


def test_number_of_groups_is_chosen_from_the_data_not_fixed():
    take, truth = so.simulate_markers("linkage", seconds=8, rate_hz=60, seed=4, noise_m=0.001, per_body=(3, 4))
    cl = cluster_markers(take.markers)
    assert cl.n_groups == 6
    assert same_partition(cl.labels, truth_bodies(take, truth))


def test_clustering_survives_marker_swaps_in_part_of_the_take():
    take, truth = so.simulate_markers("linkage", seconds=10, rate_hz=60, seed=5, noise_m=0.001, per_body=(3, 4), n_swaps=2)
    assert truth["swaps"]
    cl = cluster_markers(take.markers)
    assert same_partition(cl.labels, truth_bodies(take, truth))


def test_distance_spread_is_noise_level_inside_a_body_and_large_across_joints(human_take):
    take, truth = human_take
    body = truth_bodies(take, truth)
    std = distance_std(take.markers)
    same = body[:, None] == body[None, :]
    np.fill_diagonal(same, False)
    assert np.max(std[same]) < 0.005
    # Some cross-joint pairs sit near the joint and barely change distance, so compare typical values.
    assert np.median(std[~same & ~np.eye(len(body), dtype=bool)]) > 10 * np.median(std[same])


def test_jittered_samplings_stay_inside_their_window_and_differ():
    rng = np.random.default_rng(0)
    a = jittered_frames(1000, 50, 0.3, rng)
    b = jittered_frames(1000, 50, 0.3, rng)
    assert a.max() - a.min() <= 300 and len(a) > 40
    assert not np.array_equal(a, b)


def test_a_single_marker_is_refused_with_a_clear_error():
    # tried: one marker only — nothing to cluster
    with pytest.raises(ClusteringError, match="at least two markers"):
        cluster_markers(np.zeros((10, 1, 3)))
