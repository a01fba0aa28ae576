"""Test helper: per-frame joint residuals e_k = R_i c + t_i − R_j l − t_j, computed directly from the poses."""

from __future__ import annotations

import numpy as np


def joint_residuals(rotations, positions, c, l, pairs, valid=None) -> np.ndarray:
    """(n, p, 3) world-frame residual of each joint (i, j) = pairs[k] at every frame; NaN where i or j is invalid.

    rotations (n, m, 3, 3), positions (n, m, 3) (or one frame, giving (p, 3)); c, l (p, 3); pairs (p, 2).
    """
    R = np.asarray(rotations, dtype=float)
    t = np.asarray(positions, dtype=float)
    single = R.ndim == 3
    if single:
        R, t = R[None], t[None]
        valid = None if valid is None else np.asarray(valid)[None]
    P = np.asarray(pairs, dtype=np.intp).reshape(-1, 2)
    c = np.asarray(c, dtype=float).reshape(-1, 3)
    l = np.asarray(l, dtype=float).reshape(-1, 3)
    i, j = P[:, 0], P[:, 1]
    e = (np.einsum("kpab,pb->kpa", R[:, i], c) + t[:, i]) - (np.einsum("kpab,pb->kpa", R[:, j], l) + t[:, j])
    if valid is not None:
        w = np.asarray(valid, dtype=bool)
        e = np.where((w[:, i] & w[:, j])[..., None], e, np.nan)
    return e[0] if single else e
