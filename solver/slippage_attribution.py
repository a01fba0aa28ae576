"""Which sensor slipped (or which two swapped), from the frames after a suspected change.

Every hypothesis is scored by how well it explains the post-change residuals of all ready joints:
"sensor s slipped" = each joint of s stepped by a constant of at least the minimum jump in s's own
frame, the other joints did not move; "a and b swapped" = exchanging their data restores every joint;
"nothing" = all joints at their baseline. Scores are Gaussian log-likelihoods with each joint's own
per-frame noise level (plus a BIC term per fitted step), so the posterior over hypotheses
gives the confidence and, for a body whose joints cannot tell two sensors apart, both candidates.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from itertools import combinations

import numpy as np


# A hypothesis must beat "nothing happened" by this many nats, and report candidates down to this share.
CANDIDATE_SHARE = 0.05


@dataclass
class Attribution:
    kind: str | None  # "slip", "swap" or None (no consistent event)
    sensor: int = -1  # slip: the most likely sensor; swap: the first of the pair
    other: int = -1  # swap: the second sensor
    candidates: list[tuple[int, float]] = field(default_factory=list)  # (sensor, posterior), best first
    confidence: float = 0.0
    joints: list[int] = field(default_factory=list)  # joint indices the event affects
    jump_m: float = 0.0
    evidence: float = 0.0  # nats by which the best hypothesis beats "nothing"


def attribute(xc: np.ndarray, xp: np.ndarray, pair_valid: np.ndarray, weight: np.ndarray, joints: np.ndarray,
              ready: np.ndarray, suspects: np.ndarray, n_sensors: int, min_jump: float, min_evidence: float,
              max_misfit: float, swapped: Callable[[np.ndarray, np.ndarray], tuple] | None = None) -> Attribution:
    """Score slip and swap hypotheses on the frames since the suspected change (see module docstring).

    xc, xp (n, p, 3): each frame's deviation from the joint's baseline in its child and parent frame;
    pair_valid (n, p); weight (n, p) 1/σ² per frame and joint; joints (p, 2) (child, parent);
    ready (p,) joints with a usable baseline; suspects (p,) joints whose test fired;
    swapped(perm, touched) -> (xc, xp) for the joints `touched` with the sensors' data permuted.
    """
    pair_valid = pair_valid & (weight > 0)
    wt = np.where(pair_valid, weight, 0.0)
    use = ready & pair_valid.any(axis=0)
    if not (use & suspects).any():
        return Attribution(None)
    nj = np.maximum(pair_valid.sum(axis=0), 1)
    sw = np.maximum(wt.sum(axis=0), 1e-300)
    xc = np.where(pair_valid[..., None], xc, 0.0)
    xp = np.where(pair_valid[..., None], xp, 0.0)
    rss0 = _rss_null(xc, xp, wt)

    def stepped(x):
        mean = (wt[..., None] * x).sum(axis=0) / sw[:, None]
        free = (wt * ((x - mean) ** 2).sum(axis=-1)).sum(axis=0)
        size = np.linalg.norm(mean, axis=1)
        return free + sw * np.maximum(min_jump - size, 0.0) ** 2, free, size

    rss_c, free_c, size_c = stepped(xc)
    rss_p, free_p, size_p = stepped(xp)
    bic = 1.5 * np.log(nj)
    gain_c = np.where(use, 0.5 * (rss_c - rss0) + bic, 0.0)
    gain_p = np.where(use, 0.5 * (rss_p - rss0) + bic, 0.0)
    m = n_sensors
    inc_c = joints[:, 0][None, :] == np.arange(m)[:, None]  # (m, p) sensor is the joint's child
    inc_p = joints[:, 1][None, :] == np.arange(m)[:, None]
    slip_cost = inc_c.astype(float) @ gain_c + inc_p.astype(float) @ gain_p  # (m,)
    possible = ((inc_c | inc_p) & use[None, :]).any(axis=1)
    slip_cost = np.where(possible, slip_cost, np.inf)

    # Swaps: only among sensors of the joints that fired; exchanging their columns must restore the joints.
    involved = np.unique(joints[suspects])
    swaps = list(combinations(involved.tolist(), 2))
    swap_cost = np.full(len(swaps), np.inf)
    if swaps and swapped is not None:
        prior = np.log(len(swaps))
        for k, (a, b) in enumerate(swaps):
            perm = np.arange(m)
            perm[[a, b]] = [b, a]
            touched = np.isin(joints, (a, b)).any(axis=1) & use
            if not touched.any():
                continue
            su, sv = swapped(perm, touched)
            pv = pair_valid[:, touched]
            rss_s = _rss_null(np.where(pv[..., None], su, 0.0), np.where(pv[..., None], sv, 0.0), wt[:, touched])
            swap_cost[k] = 0.5 * (rss_s - rss0[touched]).sum() + prior

    costs = np.concatenate([slip_cost, swap_cost])
    best = int(np.argmin(costs))
    evidence = -float(costs[best])
    if not np.isfinite(evidence) or evidence < min_evidence:
        return Attribution(None, evidence=evidence)
    post = np.exp(-(costs - costs[best]))
    post /= post.sum()
    if best >= m:
        a, b = swaps[best - m]
        touched = np.flatnonzero(np.isin(joints, (a, b)).any(axis=1))
        dev = np.sqrt(np.minimum((xc**2).sum(-1), (xp**2).sum(-1)))[:, touched]
        jump = float(np.median(dev[pair_valid[:, touched]])) if pair_valid[:, touched].any() else 0.0
        return Attribution("swap", a, b, [(a, float(post[best])), (b, float(post[best]))],
                           float(post[best]), touched.tolist(), jump, evidence)
    s = best
    mine = np.flatnonzero((inc_c[s] | inc_p[s]))
    ready_mine = mine[use[mine]]
    size = np.where(inc_c[s, ready_mine], size_c[ready_mine], size_p[ready_mine])
    free = np.where(inc_c[s, ready_mine], free_c[ready_mine], free_p[ready_mine])
    misfit = free / (3.0 * nj[ready_mine])
    if np.median(size) < min_jump or np.max(misfit) > max_misfit:
        return Attribution(None, evidence=evidence)
    order = np.argsort(-post[:m])
    cands = [(int(k), float(post[k])) for k in order if post[k] >= CANDIDATE_SHARE]
    return Attribution("slip", s, -1, cands, float(post[s]), mine.tolist(), float(np.median(size)), evidence)


def _rss_null(xc: np.ndarray, xp: np.ndarray, wt: np.ndarray) -> np.ndarray:
    """Σ over frames of the weighted squared deviation from baseline, the smaller of the two frames (p,)."""
    dc = (xc**2).sum(axis=-1)
    dp = (xp**2).sum(axis=-1)
    return (wt * np.minimum(dc, dp)).sum(axis=0)
