"""Numerical pieces of the slippage monitor's watch: joint geometry per frame, local noise from frame
differences and the window-limited GLR step test that raises a suspicion. (The baseline the test
measures from, and the test that confirms a suspicion, are `baseline`.)

Pure numpy, vectorised over frames and joints; `slippage.monitor` puts them together.
"""

from __future__ import annotations

import numpy as np


def present(indices: np.ndarray) -> np.ndarray:
    """The distinct values of non-negative integer `indices` (sensor or joint numbers), ascending: what
    np.unique gives, without the import of numpy.ma that numpy 2's np.unique makes at a process's first
    call (0.06 s of every `flockcal fit`, for a handful of small integers)."""
    x = np.asarray(indices).ravel()
    return np.flatnonzero(np.bincount(x)) if x.size else x[:0]


def touching(joints: np.ndarray, sensors) -> np.ndarray:
    """Which joints ((…, 2) sensor numbers) have one of `sensors` at an end: np.isin(joints,
    sensors).any(axis=-1), by a lookup table (np.isin's own machinery is most of its cost on a few dozen
    joints, and the slip scan asks a few hundred times per take)."""
    J = np.asarray(joints)
    s = np.asarray(sensors, dtype=np.intp).ravel()
    if not J.size or not s.size:
        return np.zeros(J.shape[:-1], dtype=bool)
    table = np.zeros(max(int(J.max()), int(s.max())) + 1, dtype=bool)
    table[s] = True
    return table[J].any(axis=-1)


def column_median(x: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """The median down each column of `x` (n, k): np.median(x, axis=0) (NaN where a column holds one), or
    with `mask` (n, k) np.nanmedian over the rows where it is True and x is not NaN (NaN where there are
    none). The same values, without the import of numpy.ma that both make at a process's first call
    (0.04 s of every `flockcal fit`)."""
    x = np.asarray(x, dtype=float)
    if mask is None:
        keep = np.ones(x.shape, dtype=bool)
        spoilt = np.isnan(x).any(axis=0)
    else:
        keep = np.asarray(mask, dtype=bool) & ~np.isnan(x)
        spoilt = np.zeros(x.shape[1:], dtype=bool)
    ranked = np.sort(np.where(keep, x, np.inf), axis=0)
    count = keep.sum(axis=0)
    lo = np.take_along_axis(ranked, np.maximum((count - 1) // 2, 0)[None], axis=0)[0]
    hi = np.take_along_axis(ranked, np.maximum(count // 2, 0)[None], axis=0)[0]
    with np.errstate(invalid="ignore"):
        middle = (lo + hi) / 2.0
    return np.where(spoilt | (count == 0), np.nan, middle)

# For a 3-D isotropic Gaussian residual with per-axis sd σ, the median of its norm is 1.5382 σ.
CHI3_MEDIAN = 1.5382


def joint_geometry(rotations: np.ndarray, positions: np.ndarray, joints: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """What a joint's residual needs from each frame, apart from its estimates: g = R_iᵀ (t_i − t_j)
    (n, p, 3) and the relative rotation Q = R_iᵀ R_j (n, p, 3, 3). With estimates c, l the child-frame
    residual is u = c + g − Q l, so a new estimate costs one product per frame, not a re-read."""
    Ri = rotations[:, joints[:, 0]]
    RiT = Ri.swapaxes(-1, -2)
    d = positions[:, joints[:, 0]] - positions[:, joints[:, 1]]
    return (RiT @ d[..., None])[..., 0], RiT @ rotations[:, joints[:, 1]]


def residual(g: np.ndarray, Q: np.ndarray, c: np.ndarray, l: np.ndarray) -> np.ndarray:
    """Child-frame residual u = c + g − Q l (n, p, 3) of cached geometry g, Q with estimates c, l (p, 3)."""
    return c[None] + g - (Q @ l[None, :, :, None])[..., 0]


def joint_frames(rotations: np.ndarray, positions: np.ndarray, joints: np.ndarray, c: np.ndarray,
                 l: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame joint residual e = R_i c + t_i − R_j l − t_j in the child's frame, u = R_iᵀ e (n, p, 3),
    and the relative rotation Q = R_iᵀ R_j (n, p, 3, 3); in the parent's frame the residual is Qᵀ u.

    A sensor that slips moves the joint centre by a constant in its own frame, so in that frame the
    residual steps by a constant while in the other frame the step turns with the joint.
    """
    g, Q = joint_geometry(rotations, positions, joints)
    return residual(g, Q, c, l), Q


def sensor_frame_residuals(rotations, positions, joints, c, l) -> tuple[np.ndarray, np.ndarray]:
    """The joint residual in the child's and in the parent's frame, each (n, p, 3)."""
    u, Q = joint_frames(rotations, positions, joints, c, l)
    return u, (Q.swapaxes(-1, -2) @ u[..., None])[..., 0]


def local_variance(x: np.ndarray, pair_valid: np.ndarray, frames: int) -> np.ndarray:
    """Per-frame, per-joint noise variance per axis (n, p) from the frame-to-frame changes of the
    residual over the last `frames` frames, the largest change left out (NaN until enough are seen).

    Differences cancel a step (it shows in one difference only: the one left out) and any offset or
    slow wander with the joint angle, while following noise that grows with range and speed. For white
    noise Δx has variance 2σ² per axis, so E‖Δx‖² = 6σ².
    """
    ok = np.zeros(pair_valid.shape, dtype=bool)
    ok[1:] = pair_valid[1:] & pair_valid[:-1]
    d2 = np.zeros(pair_valid.shape)
    d2[1:] = ((x[1:] - x[:-1]) ** 2).sum(axis=-1)
    d2 = np.where(ok, d2, 0.0)
    n, p = d2.shape
    k = max(2, min(frames, n))
    S = np.concatenate([np.zeros((k, p)), np.cumsum(d2, axis=0)])
    N = np.concatenate([np.zeros((k, p)), np.cumsum(ok, axis=0)])
    total = S[k:] - S[:-k]
    count = N[k:] - N[:-k]
    pad = np.concatenate([np.zeros((k - 1, p)), d2])
    biggest = np.lib.stride_tricks.sliding_window_view(pad, k, axis=0).max(axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        var = (total - biggest) / (6.0 * (count - 1))
    return np.where(count >= max(3, k // 3), var, np.nan)


def window_glr(x: np.ndarray, weight: np.ndarray, ends, window: int, margin: float,
               min_frames: int, earliest: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Window-limited GLR for a step of unknown 3-vector in each series, at the given end frames.

    x (L, p, 3) deviations from baseline; weight (L, p) = 1/σ² per frame (0 where invalid); ends: an int
    (the last `ends` frames) or an index array into x's first axis. For an end k and a candidate start τ
    (k − window < τ ≤ k, τ ≥ earliest[j]), the weighted mean step μ over τ..k scores
    ½ Σw · max(|μ| − margin, 0)²: nats of evidence for a step larger than `margin`, which slow drifts
    of a few mm (a fit still settling) do not reach. Returns the best score (e, p) and its start index
    (e, p), indices into x's first axis. (`glr_candidates`, then `best_step`: a caller testing later
    ends of the same series again, with other `earliest`, keeps the first and runs only the second.)
    """
    return best_step(*glr_candidates(x, weight, ends, window, margin, min_frames), earliest)


def glr_candidates(x: np.ndarray, weight: np.ndarray, ends, window: int, margin: float,
                   min_frames: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`window_glr`'s evidence for every end and candidate start, before the starts each series may not
    use yet are left out: (g (e, W, p), usable (e, W, p): a start in the series with enough frames,
    tau (e, W): the start's index). Each end's values depend on that end alone."""
    L, p = weight.shape
    A = np.concatenate([np.zeros((1, p)), np.cumsum(weight, axis=0)])
    B = np.concatenate([np.zeros((1, p, 3)), np.cumsum(weight[..., None] * x, axis=0)])
    Nf = np.concatenate([np.zeros((1, p)), np.cumsum(weight > 0, axis=0)])
    k = np.arange(L - ends, L) if np.isscalar(ends) else np.asarray(ends, dtype=np.intp)  # (e,) end frames
    tau = k[:, None] - np.arange(window)[None, :]  # (e, W) start frames
    ok = tau >= 0
    tau_c = np.clip(tau, 0, None)
    SA = A[k + 1][:, None, :] - A[tau_c]  # (e, W, p)
    SB = B[k + 1][:, None, :, :] - B[tau_c]
    SN = Nf[k + 1][:, None, :] - Nf[tau_c]
    # The window's own noise, from differences inside it (a step at τ is not among them): where it
    # is larger than the trailing estimate (noise rising as a limb speeds up), the evidence shrinks.
    live = weight > 0
    both = np.zeros((L, p), dtype=bool)
    both[1:] = live[1:] & live[:-1]
    d2 = np.zeros((L, p))
    d2[1:] = np.where(both[1:], ((x[1:] - x[:-1]) ** 2).sum(axis=-1), 0.0)
    D = np.concatenate([np.zeros((1, p)), np.cumsum(d2, axis=0)])
    ND = np.concatenate([np.zeros((1, p)), np.cumsum(both, axis=0)])
    SD = D[k + 1][:, None, :] - D[tau_c + 1]
    SND = ND[k + 1][:, None, :] - ND[tau_c + 1]
    with np.errstate(invalid="ignore", divide="ignore"):
        size = np.sqrt((SB * SB).sum(axis=-1)) / SA
        own = SD / (6.0 * SND)
        trailing = SN / SA
        factor = np.where(SND >= 2, np.minimum(1.0, trailing / own), 1.0)
    g = 0.5 * SA * np.maximum(size - margin, 0.0) ** 2 * np.nan_to_num(factor, nan=1.0)
    usable = ok[..., None] & (SN >= min_frames) & (SA > 0)
    return np.nan_to_num(g), usable, tau_c


def best_step(g: np.ndarray, usable: np.ndarray, tau: np.ndarray, earliest: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The best score (e, p) and its start (e, p) of `glr_candidates`' output, starts before `earliest`
    (p,) left out."""
    g = np.where(usable & (tau[..., None] >= earliest[None, None, :]), g, 0.0)
    best = g.argmax(axis=1)  # (e, p)
    score = np.take_along_axis(g, best[:, None, :], axis=1)[:, 0, :]
    start = np.take_along_axis(np.broadcast_to(tau[..., None], g.shape), best[:, None, :], axis=1)[:, 0, :]
    return score, start
