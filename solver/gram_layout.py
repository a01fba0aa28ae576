"""The Gram accumulator's internal layout: frames checked in, and the index tables and per-pair terms it is read by.

Pure functions of shapes and arrays, kept apart from the accumulator's state (solver/accumulator.py):
`as_frames` validates a batch, `pair_terms`/`term_index` pick each pair's 16 block terms out of a Gram.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from flockcal.solver.errors import SolverError

# Per-pair terms of one score block: n, Σ R_iᵀR_j (9, row-major), Σ R_iᵀ(t_j − t_i) (3), Σ R_jᵀ(t_i − t_j) (3).
BLOCK_TERMS = 16
@lru_cache(maxsize=8)
def below_diagonal(n: int) -> np.ndarray:
    mask = np.tri(n, n, -1, dtype=bool)
    mask.setflags(write=False)
    return mask


def as_frames(rotations, positions, valid=None, n_sensors: int | None = None):
    """(rotations (n,m,3,3), positions (n,m,3), valid (n,m) bool) from a batch or a single frame.

    Sensor-frames holding NaN or inf count as invalid, so a dropout can never poison a sum.
    """
    R = np.asarray(rotations, dtype=float)
    t = np.asarray(positions, dtype=float)
    if R.ndim == 3:
        R, t = R[None], t[None]
        if valid is not None:
            valid = np.asarray(valid)[None]
    if R.ndim != 4 or R.shape[2:] != (3, 3):
        raise SolverError(f"rotations must have shape (n, m, 3, 3) or (m, 3, 3), got {np.shape(rotations)}")
    n, m = R.shape[:2]
    if n_sensors is not None and m != n_sensors:
        raise SolverError(f"frames have {m} sensors but the accumulator was made for {n_sensors}")
    if t.shape != (n, m, 3):
        raise SolverError(f"positions must have shape ({n}, {m}, 3) to match the rotations, got {np.shape(positions)}")
    if valid is None:
        w = np.ones((n, m), dtype=bool)
    else:
        w = np.asarray(valid)
        if w.shape != (n, m):
            raise SolverError(f"valid must have shape ({n}, {m}), got {w.shape}")
        w = w.astype(bool)
    return R, t, w


@lru_cache(maxsize=8)
def all_pairs_of(m: int) -> np.ndarray:
    """(m(m−1)/2, 2) pairs i < j, row-major, read-only: cached, as triu_indices costs more than a whole
    refit step on 16 sensors and the live service asks ~30×/s."""
    i, j = np.triu_indices(m, k=1)
    P = np.stack([i, j], axis=1)
    P.setflags(write=False)
    return P


def mirrored(upper: np.ndarray) -> np.ndarray:
    n = len(upper)
    up = np.where(below_diagonal(n), 0.0, upper)
    sym = up + up.T
    sym.flat[:: n + 1] = up.flat[:: n + 1]
    return sym


def pair_terms(blocks: np.ndarray, self_terms: np.ndarray, pair_frames: np.ndarray, P: np.ndarray) -> np.ndarray:
    """(p, 16) per-pair terms w = (n, Σ R_iᵀR_j row-major, Σ R_iᵀ(t_j − t_i), Σ R_jᵀ(t_i − t_j)) from a Gram in
    the (4, m, 4, m) layout with its self terms: the parts of A and b that vary (A's diagonal blocks are n·I)."""
    i, j = P[:, 0], P[:, 1]
    Bij = blocks[:, i, :, j]  # (p, 4, 4)
    out = np.empty((len(P), BLOCK_TERMS))
    out[:, 0] = pair_frames[i, j]
    out[:, 1:10] = Bij[:, :3, :3].reshape(-1, 9)
    out[:, 10:13] = Bij[:, :3, 3] - self_terms[j, i, :3, 3]
    out[:, 13:16] = Bij[:, 3, :3] - self_terms[i, j, :3, 3]
    return out


# Reordering of the 16 terms when a pair is read as (j, i): Σ R_jᵀR_i = (Σ R_iᵀR_j)ᵀ and the b halves swap.
SWAP_TERMS = np.array([0] + [1 + 3 * c + r for r in range(3) for c in range(3)] + [13, 14, 15, 10, 11, 12])


def third_difference(W: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(‖Δ³θ‖² (q, m), usable (q, m)) of windows W (q, 4, m, 3, 3) of four consecutive frames.

    R_k = R exp([θ_k]×) under a small jitter θ_k: the third difference of the matrix is R [Δ³θ]× plus the
    motion's jerk × dt³, and ‖[v]×‖²_F = 2‖v‖². Linear in R, so no product per frame is needed.
    """
    q, m = len(W), W.shape[2]
    d3 = (THIRD_DIFFERENCE @ W.reshape(q, 4, m * 9)).reshape(q, m, 9)
    x = 0.5 * np.einsum("qmj,qmj->qm", d3, d3)
    return x, valid.all(axis=1) & np.isfinite(x)


THIRD_DIFFERENCE = np.array([-1.0, 3.0, -3.0, 1.0])


@lru_cache(maxsize=8)
def term_index(m: int) -> tuple[np.ndarray, np.ndarray]:
    """Flat indices into a (4m × 4m) Gram held as its lower triangle, row-major (internal layout, column
    q·m + a; see `_whole_blocks`), of every pair's 16 block terms (`pair_terms`) for a block with every
    sensor valid: term = G[take] − G[minus]. Element (r, c) of the symmetric Gram sits at (max, min); where
    nothing is subtracted `minus` points at (0, 4m − 1), in the zero upper triangle. Term 0 (the frame
    count) is set apart."""
    n = 4 * m
    P = all_pairs_of(m)
    i, j = P[:, 0], P[:, 1]

    def at(r, c):
        r, c = np.broadcast_arrays(r, c)
        return np.maximum(r, c) * n + np.minimum(r, c)

    take = np.zeros((len(P), BLOCK_TERMS), dtype=np.intp)
    minus = np.full((len(P), BLOCK_TERMS), n - 1, dtype=np.intp)
    q = np.arange(3)
    take[:, 1:10] = at(q[None, :, None] * m + i[:, None, None], q[None, None, :] * m + j[:, None, None]).reshape(-1, 9)
    take[:, 10:13] = at(q[None] * m + i[:, None], 3 * m + j[:, None])  # Σ R_iᵀ t_j
    minus[:, 10:13] = at(q[None] * m + i[:, None], 3 * m + i[:, None])  # Σ R_iᵀ t_i
    take[:, 13:16] = at(q[None] * m + j[:, None], 3 * m + i[:, None])  # Σ R_jᵀ t_i
    minus[:, 13:16] = at(q[None] * m + j[:, None], 3 * m + j[:, None])  # Σ R_jᵀ t_j
    for x in (take, minus):
        x.setflags(write=False)
    return take, minus
