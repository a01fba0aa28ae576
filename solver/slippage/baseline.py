"""A joint's residual as a smooth function of the body's configuration: the slippage monitor's baseline
and its confirming test (is there a step at the onset that no such function explains?). Soft-tissue
artefact moves a skin sensor with the angles of the joints at either end of its segment and brings it
back when they come back; a slip is a step that stays.

The regressors are the joint's own relative rotation (all nine entries: that also re-fits a loosely
placed joint, whose residual is affine in it), the rotations of the joints next to it (three components
each, linearised about a reference pose, in the baseline; all nine, which follow soft tissue to
second order in the angles, in the confirming test) and, in the confirming test, a slow trend.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flockcal.solver.slippage.stats import CHI3_MEDIAN, column_median, present


def neighbours(joints: np.ndarray) -> np.ndarray:
    """For each joint (p, 2) the other joints that share a sensor with it (those whose angles move the
    skin under its two sensors), as an index array (p, width) padded with −1."""
    J = np.asarray(joints).reshape(-1, 2)
    share = (J[:, None, :, None] == J[None, :, None, :]).any(axis=(2, 3))
    np.fill_diagonal(share, False)
    width = int(share.sum(axis=1).max(initial=0))
    out = np.full((len(J), width), -1, dtype=np.intp)
    for j, row in enumerate(share):
        k = np.flatnonzero(row)
        out[j, :len(k)] = k
    return out


def reference_poses(Q: np.ndarray, valid: np.ndarray, row: int) -> np.ndarray:
    """Each joint's relative rotation (P, 3, 3) at its valid frame nearest `row` (the identity if none)."""
    L, P = valid.shape
    if not L:
        return np.broadcast_to(np.eye(3), (P, 3, 3)).copy()
    dist = np.where(valid, np.abs(np.arange(L) - row)[:, None], L + 1)
    pick = dist.argmin(axis=0)
    ref = Q[pick, np.arange(P)]
    return np.where(valid.any(axis=0)[:, None, None], ref, np.eye(3))


def _vee_maps(refs: np.ndarray) -> np.ndarray:
    """The linear maps (P, 3, 9) from vec(Q) (row-major) to vee(refᵀ Q), for reference rotations (P, 3, 3)."""
    M = np.zeros((len(refs), 3, 3, 3))  # (joint, component, b, c): coefficient of Q[b, c]
    M[:, 0, :, 1], M[:, 0, :, 2] = 0.5 * refs[:, :, 2], -0.5 * refs[:, :, 1]
    M[:, 1, :, 2], M[:, 1, :, 0] = 0.5 * refs[:, :, 0], -0.5 * refs[:, :, 2]
    M[:, 2, :, 0], M[:, 2, :, 1] = 0.5 * refs[:, :, 1], -0.5 * refs[:, :, 0]
    return M.reshape(len(refs), 3, 9)


def configuration_design(Q: np.ndarray, refs: np.ndarray, times: np.ndarray, onset_row: int,
                         selected: np.ndarray, nbrs: np.ndarray, trend: bool = True,
                         full: np.ndarray | None = None) -> np.ndarray:
    """Regressors (L, q, K) for the selected joints over a window of L frames.

    Q (L, P, 3, 3) of every joint, refs (P, 3, 3) reference poses; columns: 1, time from the onset (s)
    if `trend`, the joint's own Q (9 entries), all nine entries of the rotation of each neighbour in
    `full` (which follow soft tissue that grows with the square of an angle too), and for each
    neighbour in `nbrs` its rotation relative to its reference pose, linearised (3: the axial vector
    of refᵀ Q). Neighbour lists are (P, width) padded with −1; padding gives zero columns (the fit's
    ridge holds them at 0). An invalid frame's Q is zero, so are its columns.
    """
    L, P = Q.shape[:2]
    sel = np.asarray(selected, dtype=np.intp)
    nb = nbrs[sel]
    fb = np.zeros((len(sel), 0), dtype=np.intp) if full is None else full[sel]
    q, width = nb.shape
    o = 2 if trend else 1
    D = np.empty((L, q, o + 9 + 9 * fb.shape[1] + 3 * width))
    D[..., 0] = 1.0
    if trend:
        D[..., 1] = (times - times[onset_row])[:, None]
    D[..., o:o + 9] = Q[:, sel].reshape(L, q, 9)
    o += 9
    if fb.size:
        entries = np.zeros((L, P + 1, 9))  # slot P stays zero: where the −1 padding points
        used = present(fb[fb >= 0])
        entries[:, used] = Q[:, used].reshape(L, len(used), 9)
        D[..., o:o + 9 * fb.shape[1]] = entries[:, fb].reshape(L, q, -1)
        o += 9 * fb.shape[1]
    if width:
        used = present(nb[nb >= 0])
        M = refs[used].swapaxes(-1, -2)[None] @ Q[:, used]  # (L, u, 3, 3)
        rel = np.zeros((L, P + 1, 3))
        rel[:, used, 0] = 0.5 * (M[..., 2, 1] - M[..., 1, 2])
        rel[:, used, 1] = 0.5 * (M[..., 0, 2] - M[..., 2, 0])
        rel[:, used, 2] = 0.5 * (M[..., 1, 0] - M[..., 0, 1])
        D[..., o:] = rel[:, nb].reshape(L, q, 3 * width)
    return D


@dataclass
class SmoothBaseline:
    """Each joint's recent residual (child frame) as a linear function of the configuration: u ≈ const +
    Σ_k C_jk vec(Q_k) over the joint itself and its neighbours, folded into one matrix (9P, 3P) so that a
    frame's prediction for every joint is one product. Fitted on the lagged window, it follows soft
    tissue wherever the take has been before and a loosely placed joint's wander (the affine u ≈ a − Q b
    is inside it); a slip is a step that no such function follows.
    """

    const: np.ndarray  # (P, 3)
    C: np.ndarray  # (9P, 3P)
    sigma: np.ndarray  # (P,) per-axis noise sd from the median deviation, floored
    frames: np.ndarray  # (P,) valid frames the baseline came from
    refs: np.ndarray | None = None  # (P, 3, 3) the neighbours' reference poses
    inverse: np.ndarray | None = None  # (P, K, K) inverse normal matrix of the fit (unit weights)
    nbrs: np.ndarray | None = None

    def leverage(self, Q: np.ndarray) -> np.ndarray:
        """(L, P) variance of each frame's prediction in units of the fit's noise variance: about 1/N
        where the take has been before, large where the configuration is new (the fit extrapolates)."""
        if self.inverse is None:
            return np.zeros(Q.shape[:2])
        D = configuration_design(Q, self.refs, np.zeros(len(Q)), 0, np.arange(Q.shape[1]), self.nbrs, trend=False)
        return (np.matmul(D[:, :, None, :], self.inverse[None])[:, :, 0, :] * D).sum(axis=-1)

    def predict(self, Q: np.ndarray) -> np.ndarray:
        L, P = Q.shape[:2]
        return self.const[None] + (Q.reshape(L, 9 * P) @ self.C).reshape(L, P, 3)

    def deviations(self, u: np.ndarray, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Deviation of each frame from the baseline in the child frame and in the parent frame."""
        x = u - self.predict(Q)
        return x, (Q.swapaxes(-1, -2) @ x[..., None])[..., 0]

    def shift(self, dc: np.ndarray, dl: np.ndarray) -> None:
        """Follow new estimates exactly: they change every residual by δc − Q δl."""
        self.const = self.const + dc
        P = len(dc)
        own = self.C.reshape(P, 3, 3, P, 3)  # (k, b, c, j, a): coefficient of Q_k[b, c] in axis a of joint j
        idx = np.arange(P)
        for a in range(3):
            own[idx, a, :, idx, a] -= dl


def smooth_baseline(u: np.ndarray, Q: np.ndarray, mask: np.ndarray, nbrs: np.ndarray, scale_floor: float,
                    ridge: float = 1e-4, stride: int = 1) -> SmoothBaseline:
    """Least-squares `SmoothBaseline` per joint over the frames where `mask` (L, P) holds (every
    `stride`-th of them; the fit needs no more); the small ridge keeps combinations the window never
    exercised at zero, so the prediction there is what the running estimate gives."""
    u, Q, mask = u[::stride], Q[::stride], mask[::stride]
    L, P = mask.shape
    if not L:
        return SmoothBaseline(np.zeros((P, 3)), np.zeros((9 * P, 3 * P)), np.full(P, np.nan), np.zeros(P))
    sel = np.arange(P)
    refs = reference_poses(Q, mask, L - 1)
    D = configuration_design(Q, refs, np.zeros(L), L - 1, sel, nbrs, trend=False)
    wm = mask.astype(float)
    Z = np.concatenate([D, u], axis=-1) * wm[..., None]
    Zt = Z.transpose(1, 2, 0)
    G = Zt @ Zt.transpose(0, 2, 1)
    K = D.shape[-1]
    N = wm.sum(axis=0)
    A = G[:, :K, :K] + (ridge * N + 1e-12)[:, None, None] * np.eye(K)
    inverse = np.linalg.inv(A)
    sol = inverse @ G[:, :K, K:]  # (P, K, 3)
    C = np.zeros((P + 1, 9, P, 3))  # row block P catches the −1 padding
    C[sel, :, sel, :] = sol[:, 1:10, :]
    width = nbrs.shape[1]
    if width:
        maps = np.concatenate([_vee_maps(refs), np.zeros((1, 3, 9))])  # (P+1, 3, 9)
        blocks = sol[:, 10:, :].reshape(P, width, 3, 3)  # (j, slot, component, axis)
        contrib = np.einsum("jsci,jscx->jsix", maps[nbrs], blocks)  # (j, slot, 9, 3)
        np.add.at(C, (nbrs, slice(None), np.repeat(sel[:, None], width, axis=1)), contrib.transpose(0, 1, 2, 3))
    C = C[:P]
    base = SmoothBaseline(sol[:, 0, :], C.reshape(9 * P, 3 * P), np.full(P, np.nan), N * stride, refs, inverse, nbrs)
    x = u - base.predict(Q)
    d = np.sqrt((x * x).sum(axis=-1))
    level = column_median(d, None if mask.all() else mask)  # a joint with no valid frame: NaN, no baseline
    base.sigma = np.where(N > K, np.maximum(level / CHI3_MEDIAN, scale_floor), np.nan)
    return base


@dataclass
class StepFits:
    """Per series, the least squares without a step and what a step at the onset adds, in the form
    that lets several series share one step: with the smooth regressors eliminated, the step s costs
    RSS(s) = rss_none − 2 gᵀs + h ‖s‖² (weighted), so one series alone takes s = g / h, and series
    that must step by the same vector take Σg / Σh."""

    rss_none: np.ndarray  # (q,)
    g: np.ndarray  # (q, 3)
    h: np.ndarray  # (q,)
    after: np.ndarray  # (q,) valid frames since the onset
    weight_after: np.ndarray  # (q,) Σ 1/σ² since the onset

    @property
    def step(self) -> np.ndarray:
        """(q, 3) each series' own best step, metres."""
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.nan_to_num(self.g / self.h[:, None])

    @property
    def rss_step(self) -> np.ndarray:
        with np.errstate(invalid="ignore", divide="ignore"):
            return self.rss_none - np.nan_to_num((self.g * self.g).sum(axis=1) / self.h)


def _regularised(A: np.ndarray, ridge: float, prior_sd: float, prior_from: int) -> np.ndarray:
    """Normal matrices (q, K, K) with `step_fits`' ridge (relative to their mean diagonal) and the prior of
    sd `prior_sd` on the coefficients of columns from `prior_from` on."""
    K = A.shape[-1]
    scale = np.maximum(A.trace(axis1=1, axis2=2) / K, 1e-300)
    A = A + (ridge * scale)[:, None, None] * np.eye(K)
    if prior_sd > 0 and prior_from < K:
        A = A + np.diag(np.r_[np.zeros(prior_from), np.full(K - prior_from, 1.0 / prior_sd**2)])
    return A


def step_fits(D: np.ndarray, series: list[np.ndarray], weight: np.ndarray, after: np.ndarray,
              ridge: float = 1e-9, prior_sd: float = 0.0, prior_from: int = 0) -> list[StepFits]:
    """Least squares of each series (L, q, 3) in `series` on D (L, q, K), and what a step (after: (L,)
    bool) adds, weights (L, q) = 1/σ² (0 where a frame is not used). The coefficients of columns from
    `prior_from` on have a Gaussian prior of sd `prior_sd` (metres per unit of the regressor), so that
    a direction the window hardly moves along stays near zero instead of fitting noise (and a step).
    The series share the regressors and weights, so one Gram and one solve serve them all."""
    H = np.broadcast_to(after[:, None, None].astype(float), weight.shape + (1,))
    Z = np.concatenate([D, H, *series], axis=-1) * np.sqrt(weight)[..., None]  # (L, q, C)
    Zt = Z.transpose(1, 2, 0)
    G = Zt @ Zt.transpose(0, 2, 1)  # (q, C, C)
    K = D.shape[-1]
    q = len(G)
    ns = len(series)
    A = _regularised(G[:, :K, :K], ridge, prior_sd, prior_from)
    rhs = G[:, :K, K:]  # the step column, then the data
    sol = np.linalg.solve(A, rhs)
    data = G[:, K + 1:, K + 1:].diagonal(axis1=1, axis2=2).reshape(q, ns, 3).sum(axis=2)
    rss_none = data - (rhs[:, :, 1:] * sol[:, :, 1:]).reshape(q, K, ns, 3).sum(axis=(1, 3))
    # Schur complements of the smooth part: what is left of the step column and of its cross terms.
    h = G[:, K, K] - (rhs[:, :, 0] * sol[:, :, 0]).sum(axis=1)
    g = (G[:, K, K + 1:] - (sol[:, :, :1] * rhs[:, :, 1:]).sum(axis=1)).reshape(q, ns, 3)
    n_after = ((weight > 0) & after[:, None]).sum(axis=0)
    w_after = np.where(after[:, None], weight, 0.0).sum(axis=0)
    return [StepFits(rss_none[:, i], g[:, i], np.maximum(h, 0.0), n_after, w_after) for i in range(ns)]


def prediction_rss(D: np.ndarray, series: np.ndarray, weight: np.ndarray, after: np.ndarray,
                   ridge: float = 1e-9) -> np.ndarray:
    """Weighted RSS (q,) over the frames `after` the onset of the smooth fit made on the frames before
    it: how far the data since the onset stray from what the configuration predicts. A model fitted
    across the onset could follow a jump in its regressors (data of two bodies exchanged makes one)."""
    before = ~after
    Zb = np.concatenate([D, series], axis=-1)[before] * np.sqrt(weight[before])[..., None]
    Zt = Zb.transpose(1, 2, 0)
    G = Zt @ Zt.transpose(0, 2, 1)
    K = D.shape[-1]
    coef = np.linalg.solve(_regularised(G[:, :K, :K], ridge, 0.0, 0), G[:, :K, K:])  # (q, K, 3)
    err = series[after] - np.einsum("lqk,qka->lqa", D[after], coef)
    return np.einsum("lq,lqa,lqa->q", weight[after], err, err)


def step_scan(D: np.ndarray, series: list[np.ndarray], weight: np.ndarray, starts: np.ndarray,
              ridge: float = 1e-9, prior_sd: float = 0.0, prior_from: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """`step_fits`' g and h for a step from each row in `starts` (n,) instead of one onset: g (n, q,
    len(series), 3), h (n, q). The smooth part's normal matrix does not depend on where the step
    starts, so one factorisation serves every start; the step column's cross products are suffix sums."""
    q = D.shape[1]
    X = np.concatenate(series, axis=-1)  # (L, q, 3·ns)
    wD = D * weight[..., None]
    A = _regularised(np.einsum("lqk,lqj->qkj", wD, D), ridge, prior_sd, prior_from)
    r = np.einsum("lqk,lqa->qka", wD, X)  # (q, K, 3·ns)
    sol_x = np.linalg.solve(A, r)
    # Suffix sums from each start: Σ_{l ≥ k} w D, Σ w, Σ w x.
    b = np.cumsum(wD[::-1], axis=0)[::-1][starts]  # (n, q, K)
    c = np.cumsum(weight[::-1], axis=0)[::-1][starts]  # (n, q)
    e = np.cumsum((X * weight[..., None])[::-1], axis=0)[::-1][starts]  # (n, q, 3·ns)
    sol_b = np.linalg.solve(A[None], b[..., None])[..., 0]  # (n, q, K)
    h = c - (b * sol_b).sum(axis=-1)
    g = e - np.einsum("nqk,qka->nqa", b, sol_x)
    return g.reshape(len(starts), q, len(series), 3), np.maximum(h, 0.0)
