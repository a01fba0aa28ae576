"""Test helper: hierarchical poses (each body relative to its parent) composed into world poses and back
(paper eq. 4), to build and check takes from a tree's local motion."""

from __future__ import annotations

import numpy as np

from flockcal.solver.errors import SolverError


def to_global(rotations, positions, parent) -> tuple[np.ndarray, np.ndarray]:
    """Compose hierarchical poses into world poses: R_i = R_p R_i^rel, t_i = R_p t_i^rel + t_p (paper eq. 4).

    rotations (n, m, 3, 3) / positions (n, m, 3) give each body relative to `parent[i]` (−1: relative to
    the world). Returns world rotations and positions of the same shapes.
    """
    R = np.array(rotations, dtype=float)
    t = np.array(positions, dtype=float)
    par = np.asarray(parent, dtype=int)
    m = R.shape[-3]
    if par.shape != (m,):
        raise SolverError(f"parent must list one entry per body ({m}), got shape {par.shape}")
    done = par < 0
    order: list[int] = []
    # Bodies in an order where parents come first (m passes at most; a cycle stops the loop).
    for _ in range(m):
        ready = np.flatnonzero(~done & (par >= 0) & done[np.maximum(par, 0)])
        if not len(ready):
            break
        order.extend(ready.tolist())
        done[ready] = True
    if not done.all():
        raise SolverError("the parent map has a cycle; a hierarchy must be a tree")
    for i in order:  # one pass per body, vectorised over frames
        p = par[i]
        t[..., i, :] = np.einsum("...ab,...b->...a", R[..., p, :, :], t[..., i, :]) + t[..., p, :]
        R[..., i, :, :] = R[..., p, :, :] @ R[..., i, :, :]
    return R, t


def to_local(rotations, positions, parent) -> tuple[np.ndarray, np.ndarray]:
    """The inverse of `to_global`: each body's pose relative to its parent."""
    R = np.asarray(rotations, dtype=float)
    t = np.asarray(positions, dtype=float)
    par = np.asarray(parent, dtype=int)
    kids = np.flatnonzero(par >= 0)
    Rl, tl = R.copy(), t.copy()
    Rp = R[..., par[kids], :, :]
    Rl[..., kids, :, :] = np.swapaxes(Rp, -1, -2) @ R[..., kids, :, :]
    tl[..., kids, :] = np.einsum("...kba,...kb->...ka", Rp, t[..., kids, :] - t[..., par[kids], :])
    return Rl, tl
