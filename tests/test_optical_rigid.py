"""`rigid_fit`, the per-frame rigid transform every optical step uses: known poses recovered, the best
proper rotation when the points are mirrored, unusable frames (too few points, collinear) refused.

Its fast path (Horn's quaternion, vectorised) must equal a textbook Kabsch SVD to floating-point noise: the
oracle below is that SVD, written here from the formula, with scipy's Rotation for the true poses."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from flockcal.solver.optical.rigid import rigid_fit

# Rotations agree with the SVD's to ~1e-12 on random clusters; 1e-9 is the promise with margin.
TOL = 1e-9


def kabsch(ref: np.ndarray, obs: np.ndarray) -> np.ndarray:
    """Best proper rotations (n,3,3) of complete clouds, by the SVD: V diag(1, 1, det) Uᵀ."""
    P = ref - ref.mean(-2, keepdims=True)
    X = obs - obs.mean(-2, keepdims=True)
    U, _, Vt = np.linalg.svd(np.swapaxes(P, -1, -2) @ X)
    V = np.swapaxes(Vt, -1, -2)
    D = np.broadcast_to(np.eye(3), U.shape).copy()
    D[:, 2, 2] = np.linalg.det(V @ np.swapaxes(U, -1, -2))
    return V @ D @ np.swapaxes(U, -1, -2)


def test_known_poses_are_recovered_with_gaps():
    # Tried: 3-6 markers 5 cm apart, 2000 random poses, 1 m translations, 10 % of points hidden.
    rng = np.random.default_rng(3)
    n = 2000
    for q in (3, 4, 6):
        ref = rng.normal(size=(q, 3)) * 0.05
        R_true = Rotation.random(n, random_state=rng).as_matrix()
        t_true = rng.normal(size=(n, 3))
        obs = ref @ R_true.transpose(0, 2, 1) + t_true[:, None]
        obs[rng.random((n, q)) < 0.1] = np.nan
        R, t, ok = rigid_fit(ref, obs)
        enough = np.isfinite(obs).all(-1).sum(1) >= 3
        assert np.array_equal(ok, enough)
        assert np.abs(R[ok] - R_true[ok]).max() < TOL
        assert np.abs(t[ok] - t_true[ok]).max() < TOL


def test_noisy_and_mirrored_clouds_match_the_svd():
    # Tried: 1 mm and 3 cm of noise on 3-5 markers, and the observed cloud mirrored (det −1: no rotation
    # fits, the best proper one is wanted); also rotations proper (det +1) throughout.
    rng = np.random.default_rng(4)
    n = 3000
    for q, noise, mirror in [(3, 0.001, False), (5, 0.03, False), (4, 0.001, True), (3, 0.01, True)]:
        ref = rng.normal(size=(n, q, 3)) * 0.05
        R_true = Rotation.random(n, random_state=rng).as_matrix()
        obs = ref @ R_true.transpose(0, 2, 1) + rng.normal(size=(n, q, 3)) * noise
        if mirror:
            obs[..., 0] *= -1.0
        R, t, ok = rigid_fit(ref, obs)
        assert ok.all()
        assert np.abs(np.linalg.det(R) - 1.0).max() < TOL
        assert np.abs(R - kabsch(ref, obs)).max() < 1e-6  # random clusters include a few badly shaped ones
        assert np.median(np.abs(R - kabsch(ref, obs)).max((1, 2))) < TOL


def test_collinear_or_too_few_points_are_not_ok():
    # Tried: three markers on one line (the turn about it is free), two markers, none seen.
    rng = np.random.default_rng(5)
    n = 50
    line = np.array([[0.0, 0.0, 0.0], [0.03, 0.01, 0.0], [0.09, 0.03, 0.0]])
    R_true = Rotation.random(n, random_state=rng).as_matrix()
    obs = line @ R_true.transpose(0, 2, 1) + rng.normal(size=(n, 1, 3))
    assert not rigid_fit(line, obs)[2].any()
    tri = np.array([[0.0, 0.0, 0.0], [0.05, 0.0, 0.0], [0.0, 0.04, 0.0]])
    obs = tri @ R_true.transpose(0, 2, 1)
    obs[:25, 2] = np.nan
    obs[40:] = np.nan
    ok = rigid_fit(tri, obs)[2]
    assert not ok[:25].any() and ok[25:40].all() and not ok[40:].any()
