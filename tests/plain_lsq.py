"""The textbook yardstick for every joint decision: the stacked 3n×6 system of O'Brien et al. (eq. 15)
solved by SVD with a fixed 1.5 % relative cut-off (what SCoRE computes too).

Written apart from flockcal.solver on purpose: it shares no constant and no code with production, so a
decision rule in the solver can be held to "never worse than plain least squares".
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

RELATIVE_CUTOFF = 0.015  # singular values below 1.5 % of the largest are treated as zero


class PlainFit(NamedTuple):
    c: np.ndarray  # (3,) joint centre in sensor i's frame, metres
    l: np.ndarray  # (3,) the same point in sensor j's frame
    rank: int  # singular values kept: 6 ball, 5 hinge
    singular_values: np.ndarray  # (6,) ÷ √n, descending
    axis_i: np.ndarray  # (3,) the dropped direction in i's frame when rank == 5, else NaN
    axis_j: np.ndarray
    rms: float  # metres, sqrt(Σ‖e‖²/n)
    n: int


def plain_fit(rot_i, pos_i, rot_j, pos_j, valid=None, cutoff: float = RELATIVE_CUTOFF) -> PlainFit:
    """The minimum-norm least-squares joint of sensors i and j ((n,3,3) rotations, (n,3) positions)."""
    Ri, ti, Rj, tj = (np.asarray(a, dtype=float) for a in (rot_i, pos_i, rot_j, pos_j))
    if valid is not None:
        keep = np.asarray(valid, dtype=bool)
        Ri, ti, Rj, tj = Ri[keep], ti[keep], Rj[keep], tj[keep]
    n = len(Ri)
    A = np.concatenate([Ri, -Rj], axis=2).reshape(3 * n, 6)
    d = (tj - ti).reshape(3 * n)
    U, w, Vt = np.linalg.svd(A, full_matrices=False)
    k = int((w >= cutoff * w[0]).sum())
    u = Vt[:k].T @ ((U[:, :k].T @ d) / w[:k])
    e = A @ u - d
    ai = aj = np.full(3, np.nan)
    if k == 5:
        ai, aj = Vt[5, :3] / np.linalg.norm(Vt[5, :3]), Vt[5, 3:] / np.linalg.norm(Vt[5, 3:])
    return PlainFit(u[:3], u[3:], k, w / np.sqrt(n), ai, aj, float(np.sqrt(e @ e / n)), n)


def plain_take_fit(take, child: str, parent: str, start_s: float | None = None) -> PlainFit:
    """`plain_fit` of one joint of a take (named sensors), optionally on the frames from `start_s` on."""
    i, j = take.names.index(child), take.names.index(parent)
    v = take.valid[:, i] & take.valid[:, j]
    if start_s is not None:
        v = v & (take.times >= start_s)
    return plain_fit(take.rotations[:, i], take.positions[:, i], take.rotations[:, j], take.positions[:, j], v)
