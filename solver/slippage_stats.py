"""Numerical pieces of the slippage monitor: joint residuals seen from each sensor of the joint, a robust
per-joint baseline (a local re-fit), local noise from frame differences, a window-limited GLR step
test and the Chow-type comparison of step and no-step re-fits that confirms it.

Pure numpy, vectorised over frames and joints; `flockcal.solver.slippage` puts them together.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

# For a 3-D isotropic Gaussian residual with per-axis sd σ, the median of its norm is 1.5382 σ.
CHI3_MEDIAN = 1.5382
MAD_TO_SD = 1.4826


def joint_frames(rotations: np.ndarray, positions: np.ndarray, joints: np.ndarray, c: np.ndarray,
                 l: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame joint residual e = R_i c + t_i − R_j l − t_j in the child's frame, u = R_iᵀ e (n, p, 3),
    and the relative rotation Q = R_iᵀ R_j (n, p, 3, 3); in the parent's frame the residual is Qᵀ u.

    A sensor that slips moves the joint centre by a constant in its own frame, so in that frame the
    residual steps by a constant while in the other frame the step turns with the joint.
    """
    Ri = rotations[:, joints[:, 0]]  # (n, p, 3, 3)
    Rj = rotations[:, joints[:, 1]]
    d = positions[:, joints[:, 0]] - positions[:, joints[:, 1]]  # (n, p, 3)
    RiT = Ri.swapaxes(-1, -2)
    Q = RiT @ Rj
    u = c[None] + (RiT @ d[..., None])[..., 0] - (Q @ l[None, :, :, None])[..., 0]
    return u, Q


def sensor_frame_residuals(rotations, positions, joints, c, l) -> tuple[np.ndarray, np.ndarray]:
    """The joint residual in the child's and in the parent's frame, each (n, p, 3)."""
    u, Q = joint_frames(rotations, positions, joints, c, l)
    return u, (Q.swapaxes(-1, -2) @ u[..., None])[..., 0]


@dataclass
class Baseline:
    """Each joint's recent residual as an affine function of its relative rotation, u ≈ a − Q b.

    That is a local re-fit of the joint (a, b correct c, l): where the running estimate is off along a
    direction the motion hardly exercises, the residual wanders with the joint angle by several mm,
    which a constant baseline would take for steps. A slip is a step that this form cannot follow.
    """

    a: np.ndarray  # (p, 3) child frame
    b: np.ndarray  # (p, 3) parent frame
    sigma: np.ndarray  # (p,) per-axis noise sd from the median deviation, floored
    frames: np.ndarray  # (p,) valid frames the baseline came from

    def deviations(self, u: np.ndarray, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Deviation of each frame from the baseline in the child frame and in the parent frame."""
        x = u - self.a + (Q @ self.b[None, :, :, None])[..., 0]
        return x, (Q.swapaxes(-1, -2) @ x[..., None])[..., 0]


def affine_baseline(u: np.ndarray, Q: np.ndarray, mask: np.ndarray, scale_floor: float,
                    ridge: float = 1e-4) -> Baseline:
    """Least-squares (a, b) per joint over the frames where `mask` (n, p) holds; the small ridge on b
    keeps directions the window never exercised at the running estimate."""
    n, p = mask.shape
    wm = mask.astype(float)
    N = wm.sum(axis=0)
    SQ = np.einsum("np,npab->pab", wm, Q)
    A = np.zeros((p, 6, 6))
    eye = np.eye(3)
    A[:, :3, :3] = N[:, None, None] * eye
    A[:, 3:, 3:] = (N * (1.0 + ridge) + 1e-12)[:, None, None] * eye
    A[:, :3, 3:] = -SQ
    A[:, 3:, :3] = -SQ.transpose(0, 2, 1)
    A[:, :3, :3] += 1e-12 * eye
    rhs = np.concatenate([np.einsum("np,npa->pa", wm, u), -np.einsum("np,npba,npb->pa", wm, Q, u)], axis=1)
    sol = np.linalg.solve(A, rhs[..., None])[..., 0]
    base = Baseline(sol[:, :3], sol[:, 3:], np.full(p, np.nan), N)
    x, _ = base.deviations(u, Q)
    d = np.where(mask, np.linalg.norm(x, axis=-1), np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a joint with no valid frame has no baseline
        level = np.nanmedian(d, axis=0) if n else np.full(p, np.nan)
    # Six fitted parameters use up a little of the spread; over hundreds of frames that is negligible.
    base.sigma = np.where(N > 6, np.maximum(level / CHI3_MEDIAN, scale_floor), np.nan)
    return base


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


def window_glr(x: np.ndarray, weight: np.ndarray, ends: int, window: int, margin: float,
               min_frames: int, earliest: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Window-limited GLR for a step of unknown 3-vector in each series, at each of the last `ends` frames.

    x (L, p, 3) deviations from baseline; weight (L, p) = 1/σ² per frame (0 where invalid). For an end k
    and a candidate start τ (k − window < τ ≤ k, τ ≥ earliest[j]), the weighted mean step μ over τ..k
    scores ½ Σw · max(|μ| − margin, 0)²: nats of evidence for a step larger than `margin`, which
    slow drifts of a few mm (a fit still settling) do not reach. Returns the best score (ends, p) and
    its start index (ends, p), indices into x's first axis.
    """
    L, p = weight.shape
    A = np.concatenate([np.zeros((1, p)), np.cumsum(weight, axis=0)])
    B = np.concatenate([np.zeros((1, p, 3)), np.cumsum(weight[..., None] * x, axis=0)])
    Nf = np.concatenate([np.zeros((1, p)), np.cumsum(weight > 0, axis=0)])
    k = np.arange(L - ends, L)  # (e,) end frames
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
        size = np.linalg.norm(SB, axis=-1) / SA
        own = SD / (6.0 * SND)
        trailing = SN / SA
        factor = np.where(SND >= 2, np.minimum(1.0, trailing / own), 1.0)
    g = 0.5 * SA * np.maximum(size - margin, 0.0) ** 2 * np.nan_to_num(factor, nan=1.0)
    allowed = ok[..., None] & (SN >= min_frames) & (tau_c[..., None] >= earliest[None, None, :]) & (SA > 0)
    g = np.where(allowed, np.nan_to_num(g), 0.0)
    best = g.argmax(axis=1)  # (e, p)
    score = np.take_along_axis(g, best[:, None, :], axis=1)[:, 0, :]
    start = np.take_along_axis(np.broadcast_to(tau_c[..., None], g.shape), best[:, None, :], axis=1)[:, 0, :]
    return score, start


def step_design_sums(u: np.ndarray, Q: np.ndarray, weight: np.ndarray, step: str | None) -> np.ndarray:
    """Σ_k w_k M_kᵀ M_k per joint (p, K, K) for the model u_k = a − Q_k b (+ step) with the data as the
    last column: M_k = [I, −Q_k, u_k] (K = 7), or with a step column block after −Q_k: I for a step
    of a (the child's placement, constant in the child frame) or Q_k for a step of b (the parent's)."""
    n, p = weight.shape
    eye = np.broadcast_to(np.eye(3), (n, p, 3, 3))
    blocks = [eye, -Q]
    if step == "child":
        blocks.append(eye)
    elif step == "parent":
        blocks.append(Q)
    blocks.append(u[..., None])
    M = np.concatenate(blocks, axis=-1)  # (n, p, 3, K)
    return np.einsum("np,npik,npil->pkl", weight, M, M)


def least_squares_rss(G: np.ndarray, ridge: float = 1e-9) -> tuple[np.ndarray, np.ndarray]:
    """Minimum weighted residual sum of squares and the solution for augmented Grams G (p, K, K)
    (data in the last row/column); directions the data never exercised are held at zero."""
    A = G[:, :-1, :-1]
    g = G[:, :-1, -1]
    scale = np.maximum(np.trace(A, axis1=1, axis2=2) / A.shape[1], 1e-300)
    A = A + (ridge * scale)[:, None, None] * np.eye(A.shape[1])
    sol = np.linalg.solve(A, g[..., None])[..., 0]
    return G[:, -1, -1] - np.einsum("pk,pk->p", g, sol), sol


def chow_rss(pre: np.ndarray, u: np.ndarray, Q: np.ndarray, weight: np.ndarray) -> dict:
    """RSS of three models over the baseline window (`pre`: its (p, 7, 7) sums) and the frames since a
    suspected change: one (a, b) throughout ("none"), a step of a after the change ("child") or of b
    ("parent"). Also the fitted step sizes. Motion that merely exercises a joint in a new way is
    explained by "none" (a better a, b), which a test against a fixed baseline would call a step."""
    post = {k: step_design_sums(u, Q, weight, k) for k in ("child", "parent")}
    keep = list(range(6)) + [9]
    null = pre + post["child"][:, keep][:, :, keep]
    out = {"none": least_squares_rss(null)[0]}
    for k, G in post.items():
        full = G.copy()
        full[np.ix_(range(len(G)), keep, keep)] += pre
        rss, sol = least_squares_rss(full)
        out[k] = rss
        out[k + "_size"] = np.linalg.norm(sol[:, 6:9], axis=1)
    return out
