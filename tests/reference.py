"""Test and benchmark oracle: the paper's per-pair solve, kept as the yardstick: stack the 3n×6 system, SVD, zero small singular values.

O'Brien et al. 2000, eq. 15: [R_i, −R_j] (c, l) = t_j − t_i for every frame; the minimum-norm least-squares
solution through the SVD. Slow (one SVD of a 3n×6 matrix per pair) but with no normal equations in sight.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

# Squared singular values of the 3n×6 system ÷ n at or below this are rounding, not rotation: A/n's
# eigenvalues lie in [0, 2], and double-precision sums leave ~1e-15 where the data hold nothing. Stated
# here on its own (not read from the solver), so the yardstick shares no constant with what it measures.
FLOOR = 1e-10


class ReferenceFit(NamedTuple):
    c: np.ndarray  # (3,) in i's frame
    l: np.ndarray  # (3,) in j's frame
    singular_values: np.ndarray  # (6,) ÷ √n, descending
    rank: int
    axis_i: np.ndarray  # (3,) the last kept-out direction in i's frame (NaN unless rank == 5)
    axis_j: np.ndarray
    rms: float
    epsilon: float
    n: int


def reference_pair_fit(rot_i, pos_i, rot_j, pos_j, valid=None, floor: float = FLOOR) -> ReferenceFit:
    """Fit the joint between sensors i and j from (n,3,3) rotations and (n,3) positions by a direct SVD.

    Singular values w with (w/√n)² ≤ `floor` are zeroed (the rule `pair_fits` also follows, with its own
    constant): the rank is the oracle's own decision, never read from the fit under test. `valid` (n,) selects frames.
    """
    Ri, ti = np.asarray(rot_i, float), np.asarray(pos_i, float)
    Rj, tj = np.asarray(rot_j, float), np.asarray(pos_j, float)
    if valid is not None:
        sel = np.asarray(valid, bool)
        Ri, ti, Rj, tj = Ri[sel], ti[sel], Rj[sel], tj[sel]
    n = len(Ri)
    Q = np.concatenate([Ri, -Rj], axis=2).reshape(3 * n, 6)
    d = (tj - ti).reshape(3 * n)
    U, w, Vt = np.linalg.svd(Q, full_matrices=False)
    s = w / np.sqrt(n)
    k = int((s**2 > floor).sum())
    winv = np.zeros(6)
    winv[:k] = 1.0 / w[:k]
    u = Vt.T @ (winv * (U.T @ d))
    e = Q @ u - d
    sse = float(e @ e)
    ai = aj = np.full(3, np.nan)
    if k == 5:
        v = Vt[5]
        ai, aj = v[:3] / np.linalg.norm(v[:3]), v[3:] / np.linalg.norm(v[3:])
        sgn = np.sign(ai[np.abs(ai).argmax()]) or 1.0
        ai, aj = ai * sgn, aj * sgn
    return ReferenceFit(u[:3], u[3:], s, k, ai, aj, np.sqrt(sse / n), np.sqrt(sse) / n, n)
