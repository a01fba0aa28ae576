"""Numerical pieces of the slippage monitor: joint residuals seen from each sensor of the joint, a robust
per-joint baseline (median / MAD) and a CUSUM run over many joints and frames at once.

Pure numpy, vectorised over frames and joints; `flockcal.solver.slippage` puts them together.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# For a 3-D isotropic Gaussian residual with per-axis sd σ, the median of its norm is 1.5382 σ.
CHI3_MEDIAN = 1.5382
MAD_TO_SD = 1.4826


def sensor_frame_residuals(rotations: np.ndarray, positions: np.ndarray, joints: np.ndarray,
                           c: np.ndarray, l: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame joint residual e = R_i c + t_i − R_j l − t_j, expressed in the child's frame (R_iᵀ e)
    and in the parent's frame (R_jᵀ e); each (n, p, 3).

    A sensor that slips moves the joint centre by a constant in its own frame, so in that frame the
    residual steps by a constant while in the other frame the step turns with the joint.
    """
    Ri = rotations[:, joints[:, 0]]  # (n, p, 3, 3)
    Rj = rotations[:, joints[:, 1]]
    d = positions[:, joints[:, 0]] - positions[:, joints[:, 1]]  # (n, p, 3)
    e = (np.einsum("npab,pb->npa", Ri, c) - np.einsum("npab,pb->npa", Rj, l) + d)
    u = np.einsum("npba,npb->npa", Ri, e)
    w = np.einsum("npba,npb->npa", Rj, e)
    return u, w


def deviation(u: np.ndarray, w: np.ndarray, base_u: np.ndarray, base_w: np.ndarray) -> np.ndarray:
    """Distance of each frame's residual from the joint's baseline, the smaller of the two sensor frames
    (n, p). With a fit blended across a slip, one frame's residual is steady before the slip and the
    other's turns with the joint; the smaller deviation follows the steady one."""
    du = np.linalg.norm(u - base_u, axis=-1)
    dw = np.linalg.norm(w - base_w, axis=-1)
    return np.minimum(du, dw)


@dataclass
class Baseline:
    """Robust per-joint reference level of the residual, from a window of recent frames."""

    base_u: np.ndarray  # (p, 3) median residual in the child frame
    base_w: np.ndarray  # (p, 3) median residual in the parent frame
    level: np.ndarray  # (p,) median deviation
    scale: np.ndarray  # (p,) robust sd of the deviation (1.4826 MAD), floored
    sigma: np.ndarray  # (p,) per-axis noise sd implied by the median deviation, floored
    frames: np.ndarray  # (p,) valid frames the baseline came from


def robust_baseline(u: np.ndarray, w: np.ndarray, mask: np.ndarray, scale_floor: float) -> Baseline:
    """Median / MAD baseline per joint from frames where `mask` (n, p) holds; NaN where none."""
    mu = np.where(mask[..., None], u, np.nan)
    mw = np.where(mask[..., None], w, np.nan)
    count = mask.sum(axis=0)
    p = u.shape[1]
    if u.shape[0] == 0 or not count.any():
        nan3, nan = np.full((p, 3), np.nan), np.full(p, np.nan)
        return Baseline(nan3, nan3.copy(), nan, nan.copy(), nan.copy(), count)
    with np.errstate(all="ignore"), _quiet_nan_warnings():
        base_u = np.nanmedian(mu, axis=0)
        base_w = np.nanmedian(mw, axis=0)
        d = np.where(mask, deviation(u, w, base_u, base_w), np.nan)
        level = np.nanmedian(d, axis=0)
        mad = np.nanmedian(np.abs(d - level), axis=0)
    scale = np.maximum(MAD_TO_SD * mad, scale_floor)
    # The deviation is the smaller of two near-χ3 norms, whose median is about 0.77 × 1.538 σ.
    sigma = np.maximum(level / (0.77 * CHI3_MEDIAN), scale_floor)
    return Baseline(base_u, base_w, level, scale, sigma, count)


class _quiet_nan_warnings:
    """Silence numpy's all-NaN-slice warnings: a joint with no valid frame simply has no baseline."""

    def __enter__(self):
        import warnings

        self._ctx = warnings.catch_warnings()
        self._ctx.__enter__()
        warnings.simplefilter("ignore", RuntimeWarning)

    def __exit__(self, *exc):
        return self._ctx.__exit__(*exc)


def cusum(x: np.ndarray, s0: np.ndarray, onset0: np.ndarray, first_index: int) -> tuple[np.ndarray, np.ndarray]:
    """One-sided CUSUM S_k = max(0, S_(k−1) + x_k) over frames (axis 0) for every joint at once.

    x (n, p) increments; s0 (p,) the sums carried in; onset0 (p,) the global frame index where each
    carried run began. Returns S (n, p) and onset (n, p): the global index of the first frame of the
    run each S_k belongs to (the frame after the last reset). Uses S_k = C_k − min(0, min_(i≤k) C_i)
    with C the running sum, so there is no loop over frames.
    """
    n, p = x.shape
    C = s0[None, :] + np.cumsum(x, axis=0)
    M = np.minimum(np.minimum.accumulate(C, axis=0), 0.0)
    S = C - M
    idx = np.arange(n)[:, None] + first_index
    reset = np.where(C <= M, idx, -1)
    last = np.maximum.accumulate(reset, axis=0)
    start = np.where(s0 > 0, onset0, first_index)
    onset = np.where(last >= 0, last + 1, start[None, :])
    return S, onset
