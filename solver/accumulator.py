"""The all-pairs Gram accumulator of docs/design.md §2: one 4m×4m matrix from which every pair's normal equations are read.

Frames are summed in blocks into G = Σ X_kᵀX_k, plus each sensor's self terms restricted to the frames where
the other sensor of a pair is valid, and the two statistics a fit needs to judge itself from the data (§3a):
each sensor's rotation jitter and every pair's block moments (for standard errors that hold when residuals
are correlated in time). Accumulators copy, merge (add), subtract (windows) and optionally forget, so a live
stream, one batch and an archive split across workers all give the same sums.
"""

from __future__ import annotations

from collections.abc import Mapping
from types import MappingProxyType

import numpy as np

from flockcal.solver.blas import dsyrk

from flockcal.rotations import nearest_rotation
from flockcal.solver import rotation_jitter as jitter
from flockcal.solver.errors import SolverError
from flockcal.solver.gram_layout import (
    BLOCK_TERMS,
    SWAP_TERMS,
    all_pairs_of,
    as_frames,
    below_diagonal,
    mirrored,
    pair_terms,
    term_index,
    third_difference,
)

# Frames per block: big enough for BLAS to run at full speed, small enough that the block stays in cache.
BLOCK = 256
# Frames per score block: the unit of the batch-means standard error (docs/design.md §3a). About half a second of
# tracker data, long enough to hold the time correlation of soft-tissue residuals; BLOCK is a multiple.
SCORE_BLOCK = 64
# Finished score blocks wait in a list and are folded into the moments together (one product per pair for
# many blocks instead of one per block); at most this many all-valid blocks' Grams wait in `_gram_buf`.
_FOLD_EVERY = 128
# ... and at most this many blocks' terms wait in `_waiting`. Copies share the waiting terms and the moments
# rather than folding (a fold makes a new moments array, 240 kB at 16 sensors): the live service's 150
# segment snapshots (solver/segments.py) then hold a few moments arrays between them, not one per fold the
# refits happened to trigger, which made their memory grow with the machine's load up to 36 MB.
_SHARED_WAITING = 16


class GramAccumulator:
    """Σ X_kᵀX_k over frames, with X_k = [R_k^0 … R_k^(m−1) | t_k^0 … t_k^(m−1)] (3 × 4m), in blocks.

    Internally the columns are ordered (q, a) — column q of sensor a's [R | t], q = 0..3 — so a block of
    frames is copied into X with two strided assignments; `.gram` returns the documented layout.
    Invalid sensor-frames are zeroed columns, so every cross term already counts only frames where both
    sensors are valid; `_self[j, a]` holds sensor a's own 4×4 Gram over frames where j is valid too.
    With a forgetting factor λ < 1 each frame is weighted λ^age (per frame, not per call), so frames fed
    one at a time or in one batch give the same sums.
    """

    def __init__(self, n_sensors: int, forgetting: float = 1.0, origin=None):
        if int(n_sensors) < 2:
            raise SolverError(f"an accumulator needs at least two sensors, got {n_sensors}")
        if not 0.0 < float(forgetting) <= 1.0:
            raise SolverError(f"the forgetting factor must be in (0, 1], got {forgetting}")
        m = self.n_sensors = int(n_sensors)
        self.forgetting = float(forgetting)
        self.origin = None if origin is None else np.asarray(origin, dtype=float).reshape(3).copy()
        self._gram = np.zeros((4 * m, 4 * m))
        self._sym = None  # `_full()`'s mirrored copy of `_gram`, until the sums next change
        self._self = np.zeros((m, m, 4, 4))
        self._pair_frames = np.zeros((m, m))
        self._frames = 0
        # Work buffers (~0.8 MB at 16 sensors) come with the first update: the copies taken for every refit
        # and every segment snapshot are never fed, and need none.
        self._xbuf = self._pend_R = self._pend_t = self._pend_w = None
        self._npend = 0
        # Score blocks: the open block's Gram (upper, internal layout), self terms and pair frames, and the
        # finished blocks' moments Σ w wᵀ per pair. `_moments` is replaced, never written in place, so copies
        # (a refit's, a segment snapshot's) share it until the next block completes.
        self._open_gram = np.zeros((4 * m, 4 * m))
        self._open_self = np.zeros((m, m, 4, 4))
        self._open_pf = np.zeros((m, m))
        self._open_n = 0
        p = m * (m - 1) // 2
        self._moments = np.zeros((p, BLOCK_TERMS, BLOCK_TERMS))
        self._moment_frames = np.zeros(p)  # frames of the finished blocks, per pair
        self._moment_blocks = np.zeros(p)  # finished blocks with at least one frame of the pair
        self._waiting: list[np.ndarray] = []  # finished blocks' terms (k, p, 16), not yet in `_moments`
        # All-valid finished blocks' Grams, written by dsyrk straight into rows of one buffer (made on the
        # first such block: copies are folded first and need none); see `_whole_blocks`.
        self._gram_buf: np.ndarray | None = None
        self._n_buf = 0
        self._waiting_windows: list[tuple[np.ndarray, np.ndarray]] = []  # jitter windows not yet histogrammed
        # Rotation jitter: per-sensor histogram of third differences, and the last frames to difference with.
        self._jitter = np.zeros((m, jitter.BINS))
        # `rotation_noise()` of the histogram as it stands (None: worked out again on the next call). The
        # histogram changes a few times a second, the live service reads the noise ~90 times.
        self._noise: np.ndarray | None = None
        self._tail_R = np.zeros((0, m, 3, 3))  # the first frames of a jitter window the next block completes
        self._tail_w = np.zeros((0, m), dtype=bool)

    def _make_buffers(self) -> None:
        m = self.n_sensors
        self._xbuf = np.empty((BLOCK, 3, 4, m))
        # Small updates wait here until a block is full (or a result is read): a 1-frame update costs a copy.
        self._pend_R = np.empty((BLOCK, m, 3, 3))
        self._pend_t = np.empty((BLOCK, m, 3))
        self._pend_w = np.empty((BLOCK, m), dtype=bool)

    # -- feeding -----------------------------------------------------------------------------------
    def add_poses(self, rotations, positions, valid=None) -> "GramAccumulator":
        """Add poses: a batch (n, m, 3, 3) / (n, m, 3) / (n, m), or one frame (m, 3, 3) / (m, 3) / (m,)."""
        R, t, w = as_frames(rotations, positions, valid, self.n_sensors)
        n = R.shape[0]
        if n == 0:
            return self
        if self._xbuf is None:
            self._make_buffers()
        if self.origin is None:
            self._set_origin(t, w)
        if self._npend + n <= BLOCK:
            k = self._npend
            self._pend_R[k:k + n] = R
            self._pend_t[k:k + n] = t
            self._pend_w[k:k + n] = w
            self._npend += n
            if self._npend == BLOCK:
                self._flush()
            return self
        self._flush()
        self._accumulate(R, t, w)
        return self

    def _flush(self) -> None:
        if self._npend:
            k, self._npend = self._npend, 0
            self._accumulate(self._pend_R[:k], self._pend_t[:k], self._pend_w[:k])

    def _set_origin(self, t: np.ndarray, w: np.ndarray) -> None:
        # The first frame's centroid keeps ‖t‖² small in G, so SSE = uᵀAu − 2bᵀu + Σ‖d‖² does not cancel badly.
        rows = np.flatnonzero(w.any(axis=1))
        if rows.size:
            k = rows[0]
            pts = t[k][w[k]]
            pts = pts[np.isfinite(pts).all(axis=1)]
            if len(pts):
                self.origin = pts.mean(axis=0)

    def _accumulate(self, R: np.ndarray, t: np.ndarray, w: np.ndarray) -> None:
        if self.origin is None:
            self._set_origin(t, w)
            if self.origin is None:  # nothing valid yet: only the frame count moves
                self._decay(R.shape[0])
                self._frames += R.shape[0]
                return
        self._add_jitter(R, w, self._frames)  # once for the whole batch: its cost is mostly per call
        for s in range(0, R.shape[0], BLOCK):
            self._block(R[s:s + BLOCK], t[s:s + BLOCK], w[s:s + BLOCK])

    def _decay(self, n: int) -> np.ndarray | None:
        """Scale the sums by λ^n and return the weights λ^(n−1−k) of the n new frames (None when λ = 1)."""
        if self.forgetting == 1.0:
            return None
        f = self.forgetting ** n
        self._gram *= f
        self._sym = None
        self._self *= f
        self._pair_frames *= f
        self._open_gram *= f
        self._open_self *= f
        self._open_pf *= f
        self._fold()
        self._histogram()
        self._moments = self._moments * f * f
        self._moment_frames = self._moment_frames * f
        self._jitter *= f
        self._noise = None
        return self.forgetting ** np.arange(n - 1, -1, -1, dtype=float)

    def _block(self, R: np.ndarray, t: np.ndarray, w: np.ndarray) -> None:
        nb, m = R.shape[:2]
        buf = self._xbuf[:nb]
        buf[:, :, :3, :] = R.transpose(0, 2, 3, 1)  # X[k, r, q, a] = R_k^a[r, q]
        np.subtract(t.transpose(0, 2, 1), self.origin[None, :, None], out=buf[:, :, 3, :])
        all_valid = bool(w.all())
        if not np.isfinite(buf).all():
            w = w & np.isfinite(R).all(axis=(2, 3)) & np.isfinite(t).all(axis=2)
            all_valid = False
        if not all_valid:
            np.copyto(buf, 0.0, where=~w[:, None, None, :])  # copyto, not multiply: 0 × NaN is NaN
        omega = self._decay(nb)
        if omega is not None:
            buf *= np.sqrt(omega)[:, None, None, None]
        # The block is summed in pieces that end on score-block boundaries, so each finished score block
        # leaves its own sums behind; their total is the block's, as one dsyrk would give it.
        a = 0
        if self._open_n:
            a = min(nb, SCORE_BLOCK - self._open_n)
            self._piece(buf[:a], w[:a], all_valid, None if omega is None else omega[:a])
        whole = (nb - a) // SCORE_BLOCK
        if whole and all_valid and omega is None:  # a batch's usual case: whole blocks, every sensor valid
            self._whole_blocks(buf[a:a + whole * SCORE_BLOCK], whole)
            a += whole * SCORE_BLOCK
        while a < nb:
            b = min(nb, a + SCORE_BLOCK - self._open_n)
            self._piece(buf[a:b], w[a:b], all_valid, None if omega is None else omega[a:b])
            a = b
        self._frames += nb

    def _whole_blocks(self, buf: np.ndarray, k: int) -> None:
        """k whole score blocks with every sensor valid: each block's Gram is added to the sums and kept for
        `_fold`, which gathers every pair's terms from many blocks at a time."""
        m = self.n_sensors
        n = 4 * m
        X = buf.reshape(k, 3 * SCORE_BLOCK, n)
        if self._gram_buf is None:
            self._gram_buf = np.zeros((_FOLD_EVERY, n, n))
        total = np.zeros((n, n))
        b = 0
        while b < k:
            first = self._n_buf
            last = min(_FOLD_EVERY, first + k - b)
            for row in range(first, last):
                # dsyrk writes column-major into the transpose of a row of the buffer: the buffer then holds
                # each Gram as its lower triangle (row-major), and its strict upper triangle stays zero.
                dsyrk(1.0, X[b].T, beta=0.0, c=self._gram_buf[row].T, trans=0, overwrite_c=1)
                b += 1
            total += self._gram_buf[first:last].sum(axis=0).T
            self._n_buf = last
            if self._n_buf == _FOLD_EVERY:
                self._fold()
        self._gram += total
        self._sym = None
        diag = np.einsum("qapa->aqp", total.reshape(4, m, 4, m))
        diag = diag + np.triu(diag, 1).transpose(0, 2, 1)
        self._self += diag[None]
        self._pair_frames += k * SCORE_BLOCK
        self._moment_frames = self._moment_frames + k * SCORE_BLOCK
        self._moment_blocks = self._moment_blocks + k

    def _piece(self, buf: np.ndarray, w: np.ndarray, all_valid: bool, omega) -> None:
        nb, m = buf.shape[0], self.n_sensors
        X = buf.reshape(3 * nb, 4 * m)
        # Upper triangle of XᵀX, without a copy of X; `_gram` holds the upper triangle, mirrored on read.
        gb = dsyrk(1.0, X.T, trans=0)
        self._gram += gb
        self._open_gram += gb
        self._sym = None
        if all_valid:
            diag = np.einsum("qapa->aqp", gb.reshape(4, m, 4, m))  # upper part of each sensor's 4×4
            diag = diag + np.triu(diag, 1).transpose(0, 2, 1)
            self_terms = np.broadcast_to(diag[None], (m, m, 4, 4))
            pf = nb if omega is None else omega.sum()
        else:
            wf = w.astype(float)
            own = np.einsum("krqa,krpa->kaqp", buf, buf)  # each sensor's own 4×4 Gram per frame
            self_terms = (wf.T @ own.reshape(nb, m * 16)).reshape(m, m, 4, 4)
            pf = wf.T @ (wf if omega is None else wf * omega[:, None])
        self._self += self_terms
        self._pair_frames += pf
        self._open_self += self_terms
        self._open_pf += pf
        self._open_n += nb
        if self._open_n >= SCORE_BLOCK:
            self._close_score_block()

    def _close_score_block(self) -> None:
        """Fold the finished score block's per-pair terms into the moments Σ w wᵀ and start a new block."""
        m = self.n_sensors
        P = all_pairs_of(m)
        blocks = mirrored(self._open_gram).reshape(4, m, 4, m)
        wt = pair_terms(blocks, self._open_self, self._open_pf, P)
        self._waiting = self._waiting + [wt[None]]  # a new list: copies share the old one
        self._moment_frames = self._moment_frames + wt[:, 0]
        self._moment_blocks = self._moment_blocks + (wt[:, 0] > 0)
        self._fold_if_many()
        self._open_gram = np.zeros_like(self._open_gram)
        self._open_self = np.zeros_like(self._open_self)
        self._open_pf = np.zeros_like(self._open_pf)
        self._open_n = 0

    def _fold_if_many(self) -> None:
        if len(self._waiting) >= _SHARED_WAITING:
            self._fold()

    def _gather(self) -> None:
        """The all-valid blocks' Grams in `_gram_buf` as waiting terms (a buffer that is written again cannot
        be shared with a copy; the terms, never written once made, can)."""
        if not self._n_buf:
            return
        take, minus = term_index(self.n_sensors)
        flat = self._gram_buf[:self._n_buf].reshape(self._n_buf, -1)
        k = self._n_buf
        # np.take along an axis gathers several times faster than fancy indexing here.
        wt = np.take(flat, take.ravel(), axis=1).reshape(k, *take.shape)  # (k, p, 16)
        wt[:, :, 10:] -= np.take(flat, minus[:, 10:].ravel(), axis=1).reshape(k, len(take), 6)
        wt[:, :, 0] = SCORE_BLOCK
        self._waiting = self._waiting + [wt]
        self._n_buf = 0

    def _fold(self) -> None:
        """Add the waiting blocks' Σ w wᵀ into the moments (a new array: copies share the old one)."""
        self._gather()
        if not self._waiting:
            return
        W = np.concatenate(self._waiting).transpose(1, 0, 2)  # (p, k, 16)
        self._moments = self._moments + W.transpose(0, 2, 1) @ W
        self._waiting = []

    def _add_jitter(self, R: np.ndarray, w: np.ndarray, first: int) -> None:
        """Each sensor's third difference of its rotation over four frames, for the jitter (docs/design.md §3a).

        A third difference cancels any smooth motion (to the motion's jerk × dt³) and keeps 20× the
        per-axis jitter variance of the angles (1 + 9 + 9 + 1). Position noise does not enter: this is
        rotation noise alone. Windows start at fixed frames of the take (`first` is the global index of R's
        first frame; see solver/rotation_jitter.py), so however the frames arrive they make the same windows.
        """
        n = len(R)
        if len(self._tail_R):  # a window begun in the last block: complete it with this block's frames
            more = min(4 - len(self._tail_R), n)
            self._tail_R = np.concatenate([self._tail_R, R[:more]])
            self._tail_w = np.concatenate([self._tail_w, w[:more]])
            if len(self._tail_R) == 4:
                self._waiting_windows.append(third_difference(self._tail_R[None], self._tail_w[None]))
                self._tail_R, self._tail_w = self._tail_R[:0], self._tail_w[:0]
        starts, dense = jitter.window_starts(first, n)
        whole = starts[starts + 4 <= n]
        if len(whole) and dense == len(whole) and len(whole) * 4 == whole[-1] + 4 - whole[0]:
            span = slice(whole[0], whole[-1] + 4)  # back-to-back windows: a reshape, no gather
            W = R[span].reshape((len(whole), 4) + R.shape[1:])
            V = w[span].reshape((len(whole), 4) + w.shape[1:])
            self._waiting_windows.append(third_difference(W, V))
        elif len(whole):
            idx = whole[:, None] + np.arange(4)
            self._waiting_windows.append(third_difference(R[idx], w[idx]))
        if len(starts) > len(whole):  # a window starts in R's last frames: carry them over
            self._tail_R, self._tail_w = R[starts[-1]:].copy(), w[starts[-1]:].copy()
        if len(self._waiting_windows) >= 64:
            self._histogram()

    def _histogram(self) -> None:
        """Add the waiting windows' squared third differences (each (q, m) with valid (q, m)) to the histogram."""
        if not self._waiting_windows:
            return
        m = self.n_sensors
        x = np.concatenate([a for a, _ in self._waiting_windows])
        sel = np.concatenate([v for _, v in self._waiting_windows])
        self._waiting_windows = []
        if not sel.any():
            return
        self._jitter += jitter.bin_counts(x, sel, m)
        self._noise = None

    def ingest(self, times, rotations, positions, valid=None) -> "GramAccumulator":
        """`add_poses` in the `Accumulator` protocol's form: the frames' `times` do not matter here."""
        return self.add_poses(rotations, positions, valid)

    # -- the Accumulator protocol: a plain accumulator is its own whole take, with no segments --------
    @property
    def whole_take(self) -> "GramAccumulator":
        return self

    @property
    def segments(self) -> Mapping:
        return _NO_SEGMENTS

    def pair_view(self) -> "GramAccumulator":
        return self

    # -- results -----------------------------------------------------------------------------------
    @property
    def frames(self) -> int:
        """Frames seen (whatever their validity; not decayed)."""
        return self._frames + self._npend

    @property
    def pair_frames(self) -> np.ndarray:
        """(m, m) frames where both sensors were valid (weighted by λ^age when forgetting)."""
        self._flush()
        return self._pair_frames.copy()

    @property
    def gram(self) -> np.ndarray:
        """G = Σ X_kᵀX_k (4m × 4m) in docs/design.md's layout: rotation columns 3a..3a+2, then translation 3m+a."""
        self._flush()
        m = self.n_sensors
        a = np.arange(m)
        perm = np.concatenate([(np.arange(3)[None, :] * m + a[:, None]).ravel(), 3 * m + a])
        return self._full()[np.ix_(perm, perm)]

    def _blocks(self) -> np.ndarray:
        """The mirrored Gram as (4, m, 4, m): [q, a, p, b] pairs column q of sensor a's [R | t] with column p of b's."""
        m = self.n_sensors
        return self._full().reshape(4, m, 4, m)

    def _full(self) -> np.ndarray:
        # One refit reads the mirrored Gram several times (normal equations, placements, bones): mirror once.
        if self._sym is None:
            n = 4 * self.n_sensors
            up = np.where(below_diagonal(n), 0.0, self._gram)  # np.triu, with its mask built once per size
            sym = up + up.T
            sym.flat[:: n + 1] = up.flat[:: n + 1]  # the diagonal once, not twice
            sym.setflags(write=False)
            self._sym = sym
        return self._sym

    def normal_equations(self, pairs) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """For pairs (p, 2) of (i, j): A (p,6,6), b (p,6), Σ‖t_j − t_i‖² (p,), frames n (p,).

        The stacked system is Q_k u = d_k with Q_k = [R_i, −R_j], u = (c, l), d_k = t_j − t_i, so that
        SSE(u) = uᵀAu − 2bᵀu + Σ‖d‖², over the frames where both sensors are valid.
        """
        self._flush()
        m = self.n_sensors
        P = np.asarray(pairs, dtype=np.intp).reshape(-1, 2)
        if P.size and (P.min() < 0 or P.max() >= m):
            raise SolverError(f"pair indices must be in 0..{m - 1}")
        i, j = P[:, 0], P[:, 1]
        p = len(P)
        S = self._self
        Sji, Sij = S[j, i], S[i, j]  # sensor i's self terms over frames where j is valid, and vice versa
        Bij = self._blocks()[:, i, :, j]  # (p, 4, 4): Σ [R_i | t_i]ᵀ[R_j | t_j]
        Gij = Bij[:, :3, :3]
        A = np.empty((p, 6, 6))
        A[:, :3, :3] = Sji[:, :3, :3]
        A[:, 3:, 3:] = Sij[:, :3, :3]
        A[:, :3, 3:] = -Gij
        A[:, 3:, :3] = -Gij.transpose(0, 2, 1)
        b = np.empty((p, 6))
        b[:, :3] = Bij[:, :3, 3] - Sji[:, :3, 3]
        b[:, 3:] = Bij[:, 3, :3] - Sij[:, :3, 3]
        dd = Sji[:, 3, 3] - 2.0 * Bij[:, 3, 3] + Sij[:, 3, 3]
        return A, b, dd, self._pair_frames[i, j].copy()

    def translation_power(self, pairs) -> np.ndarray:
        """(p,) mean of ‖t_i − o‖² + ‖t_j − o‖² over the pair's frames: the size of the terms Σ‖d‖² is read from."""
        self._flush()
        P = np.asarray(pairs, dtype=np.intp).reshape(-1, 2)
        i, j = P[:, 0], P[:, 1]
        n = self._pair_frames[i, j]
        has = n > 0
        return np.where(has, (self._self[j, i, 3, 3] + self._self[i, j, 3, 3]) / np.where(has, n, 1.0), 0.0)

    def rotation_noise(self) -> np.ndarray:
        """(m,) each sensor's rotation jitter, variance per axis in rad², from the take itself (NaN until
        a few frames have arrived): the median third difference of its frame-to-frame rotation, read as
        white noise. What rotation noise alone adds to a pair's μ_k is about the sum of its two sensors'."""
        self._flush()
        self._histogram()
        if self._noise is not None:
            return self._noise
        noise = jitter.median_noise(self._jitter)
        noise.setflags(write=False)
        self._noise = noise
        return noise

    def block_moments(self, pairs) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For pairs (p, 2) of (i, j): the moments Σ_b w_b w_bᵀ (p, 16, 16) of each finished score block's
        terms w_b = (n, Σ R_iᵀR_j, Σ R_iᵀ(t_j − t_i), Σ R_jᵀ(t_i − t_j)), the frames those blocks hold
        and how many blocks had the pair. A pair's block score A_b u − b_b is linear in w_b, so these give
        the batch-means variance of any fit u (docs/design.md §3a) without keeping the blocks."""
        self._flush()
        m = self.n_sensors
        P = np.asarray(pairs, dtype=np.intp).reshape(-1, 2)
        if P.size and (P.min() < 0 or P.max() >= m):
            raise SolverError(f"pair indices must be in 0..{m - 1}")
        i, j = P[:, 0], P[:, 1]
        lo, hi = np.minimum(i, j), np.maximum(i, j)
        row = lo * m - lo * (lo + 1) // 2 + (hi - lo - 1)
        self._fold()
        Hm = self._moments[row]
        swap = i > j
        if swap.any():  # the terms of (j, i) are those of (i, j) with R_iᵀR_j transposed and the b halves swapped
            perm = SWAP_TERMS
            Hm = Hm.copy()
            Hm[swap] = Hm[swap][:, perm][:, :, perm]
        return Hm, self._moment_frames[row].copy(), self._moment_blocks[row].copy()

    def pair_point(self, point, src, dst) -> np.ndarray:
        """Mean over frames of a point fixed in sensor `src`'s frame, expressed in sensor `dst`'s frame.

        For two rigidly joined sensors this is exact: mean of R_dstᵀ(R_src x + t_src − t_dst). Vectorised
        over (k, 3) points with (k,) src and dst indices.
        """
        self._flush()
        x = np.asarray(point, dtype=float).reshape(-1, 3)
        s = np.asarray(src, dtype=np.intp).reshape(-1)
        d = np.asarray(dst, dtype=np.intp).reshape(-1)
        G = self._blocks()
        total = np.einsum("kab,kb->ka", G[:3, d, :3, s], x) + G[3, s, :3, d] - self._self[s, d, :3, 3]
        n = self._pair_frames[s, d][:, None]
        has = n > 0
        return np.where(has, total / np.where(has, n, 1.0), np.nan)

    def relative_rotation(self, src, dst) -> np.ndarray:
        """(k, 3, 3) mean over frames of R_dstᵀ R_src, projected to a rotation: maps src-frame vectors to dst."""
        self._flush()
        s = np.asarray(src, dtype=np.intp).reshape(-1)
        d = np.asarray(dst, dtype=np.intp).reshape(-1)
        return nearest_rotation(self._blocks()[:3, d, :3, s])

    # -- copies and arithmetic ---------------------------------------------------------------------
    def copy(self) -> "GramAccumulator":
        """An independent snapshot (later updates to either do not affect the other)."""
        self._flush()
        new = GramAccumulator(self.n_sensors, self.forgetting, self.origin)
        new._gram = self._gram.copy()
        new._self = self._self.copy()
        new._pair_frames = self._pair_frames.copy()
        new._frames = self._frames
        # The moments array and the waiting blocks' terms are shared, not copied: both are replaced, never
        # written (a copy folds its own when it needs its moments: `block_moments`).
        self._gather()
        self._fold_if_many()
        self._histogram()
        new._moments, new._waiting, new._moment_frames = self._moments, self._waiting, self._moment_frames.copy()
        new._moment_blocks, new._jitter = self._moment_blocks.copy(), self._jitter.copy()
        new._noise = self._noise  # read-only, and of the same histogram
        new._open_gram, new._open_self = self._open_gram.copy(), self._open_self.copy()
        new._open_pf, new._open_n = self._open_pf.copy(), self._open_n
        new._tail_R, new._tail_w = self._tail_R.copy(), self._tail_w.copy()
        return new

    def _add_statistics(self, other: "GramAccumulator", sign: float = 1.0) -> None:
        """Add (or subtract) another accumulator's jitter and finished score blocks; open blocks stay
        apart (their frames are in the Gram, and the batch-means variance scales for them)."""
        self._fold()
        other._fold()
        self._histogram()
        other._histogram()
        self._moments = self._moments + sign * other._moments
        self._moment_frames = self._moment_frames + sign * other._moment_frames
        self._moment_blocks = self._moment_blocks + sign * other._moment_blocks
        self._jitter = np.maximum(self._jitter + sign * other._jitter, 0.0)
        self._noise = None

    snapshot = copy

    def _check_compatible(self, other: "GramAccumulator") -> None:
        if not isinstance(other, GramAccumulator) or other.n_sensors != self.n_sensors:
            raise SolverError("accumulators can only be combined when they have the same number of sensors")
        if self.origin is not None and other.origin is not None and not np.array_equal(self.origin, other.origin):
            raise SolverError(
                "accumulators with different origins cannot be combined; create the workers' accumulators "
                "with the same origin= (for example the first frame's centroid)"
            )

    def merge(self, other: "GramAccumulator") -> "GramAccumulator":
        """Add another accumulator's sums into this one (frames from a second worker); returns self."""
        self._check_compatible(other)
        self._flush()
        other._flush()
        if self.origin is None:
            self.origin = None if other.origin is None else other.origin.copy()
        self._gram += other._gram
        self._sym = None
        self._self += other._self
        self._pair_frames += other._pair_frames
        self._frames += other._frames
        self._add_statistics(other)
        return self

    def __add__(self, other: "GramAccumulator") -> "GramAccumulator":
        return self.copy().merge(other)

    def __sub__(self, other: "GramAccumulator") -> "GramAccumulator":
        """The frames in self but not in an earlier snapshot `other` of it: a window (without forgetting)."""
        self._check_compatible(other)
        new = self.copy()
        other._flush()
        new._gram -= other._gram
        new._sym = None
        new._self -= other._self
        new._pair_frames -= other._pair_frames
        new._frames -= other._frames
        new._add_statistics(other, -1.0)
        return new

    def __repr__(self) -> str:
        return f"GramAccumulator(n_sensors={self.n_sensors}, frames={self.frames}, forgetting={self.forgetting})"


_NO_SEGMENTS: Mapping = MappingProxyType({})
