"""The simulator's optical mode: skin markers fixed in the bone frames, noise, occlusion gaps, swaps."""

import numpy as np

from flockcal.simulator import optical as so
from flockcal.simulator.body import bone_poses, by_name


def test_two_to_four_markers_ride_each_body_at_fixed_distances():
    model = by_name("human")
    L, root_t, times = so.smooth_local_rotations(model, 4, 60, seed=1)
    take, truth = so.simulate_markers(model, (L, root_t, times), noise_m=0.0, seed=1)
    counts = {b: list(truth["marker_body"].values()).count(b) for b in model.names}
    assert set(counts) == set(model.names) and min(counts.values()) >= 2 and max(counts.values()) <= 4
    body = np.array([model.names.index(truth["marker_body"][m]) for m in take.marker_names])
    d = np.linalg.norm(take.markers[:, :, None] - take.markers[:, None], axis=-1)
    same = (body[:, None] == body[None, :]) & ~np.eye(len(body), dtype=bool)
    assert np.max(np.std(d, axis=0)[same]) < 1e-9
    B, b = bone_poses(model, L, root_t)
    offs = np.array([truth["marker_offset"][m] for m in take.marker_names])
    np.testing.assert_allclose(so.marker_positions(B, b, body, offs), take.markers, atol=1e-12)


def test_noise_gaps_and_swaps_are_what_was_asked_for():
    clean, _ = so.simulate_markers("linkage", seconds=6, rate_hz=60, seed=2, noise_m=0.0)
    take, truth = so.simulate_markers("linkage", seconds=6, rate_hz=60, seed=2, noise_m=0.002, occlusion=0.05, n_swaps=1)
    gaps = np.isnan(take.markers).any(-1)
    assert 0.02 < gaps.mean() < 0.12
    start, stop, a, b = truth["swaps"][0]
    ia, ib = take.marker_names.index(a), take.marker_names.index(b)
    seen = ~gaps
    outside = np.ones(take.n_frames, dtype=bool)
    outside[start:stop] = False
    resid = (take.markers - clean.markers)[seen & outside[:, None]]
    assert 0.0015 < np.std(resid) < 0.0025
    both = seen[start:stop, ia] & seen[start:stop, ib]
    np.testing.assert_allclose(take.markers[start:stop, ia][both], clean.markers[start:stop, ib][both], atol=0.02)
