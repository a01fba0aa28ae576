"""Which sensor slipped (or which two swapped), from the frames after a suspected change.

Every hypothesis is scored by how well it explains the residuals of all ready joints over their
baseline window and the frames since the change, each joint re-fitted (its a, b) under the hypothesis:
"sensor s slipped" = each joint of s stepped, by at least the minimum jump, in s's own frame, the
other joints did not; "a and b swapped" = exchanging their data restores every joint; "nothing" =
one re-fit explains each joint before and after. Scores are Gaussian log-likelihoods with each joint's own
per-frame noise level (plus a BIC term per fitted step), so the posterior over hypotheses
gives the confidence and, for a body whose joints cannot tell two sensors apart, both candidates.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from itertools import combinations

import numpy as np

from flockcal.solver.slippage_stats import chow_rss


# Other sensors are listed as candidates down to this posterior share.
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


def attribute(pre: np.ndarray, u: np.ndarray, Q: np.ndarray, pair_valid: np.ndarray, weight: np.ndarray,
              joints: np.ndarray, ready: np.ndarray, suspects: np.ndarray, n_sensors: int, min_jump: float,
              min_evidence: float, swapped: Callable[[np.ndarray, np.ndarray], tuple] | None = None) -> Attribution:
    """Score slip and swap hypotheses on the frames since the suspected change (see module docstring).

    pre (p, 7, 7): each joint's weighted design sums over its baseline window (`step_design_sums`);
    u (n, p, 3), Q (n, p, 3, 3): child-frame residuals and relative rotations of the frames since the
    change, with the estimates the sums were made with; pair_valid (n, p); weight (n, p) 1/σ²;
    joints (p, 2) (child, parent); ready (p,) joints with a baseline; suspects (p,) joints that fired;
    swapped(perm, touched) -> (u, Q) of the joints `touched` with the sensors' data permuted.
    """
    pair_valid = pair_valid & (weight > 0)
    wt = np.where(pair_valid, weight, 0.0)
    use = ready & pair_valid.any(axis=0)
    if not (use & suspects).any():
        return Attribution(None)
    nj = np.maximum(pair_valid.sum(axis=0), 1)
    sw = wt.sum(axis=0)
    u = np.where(pair_valid[..., None], u, 0.0)
    rss = chow_rss(pre, u, Q, wt)
    bic = 1.5 * np.log(nj)

    def gain(role):
        short = np.maximum(min_jump - rss[role + "_size"], 0.0)
        g = 0.5 * (rss[role] - rss["none"]) + bic + 0.5 * sw * short**2
        return np.where(use, g, 0.0)

    gain_c, gain_p = gain("child"), gain("parent")
    m = n_sensors
    inc_c = joints[:, 0][None, :] == np.arange(m)[:, None]  # (m, p) sensor is the joint's child
    inc_p = joints[:, 1][None, :] == np.arange(m)[:, None]
    slip_cost = inc_c.astype(float) @ gain_c + inc_p.astype(float) @ gain_p  # (m,)
    possible = ((inc_c | inc_p) & use[None, :]).any(axis=1)
    slip_cost = np.where(possible, slip_cost, np.inf)

    # Swaps: only among sensors of the joints that fired; exchanging their data must restore the joints.
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
            su, sQ = swapped(perm, touched)
            su = np.where(pair_valid[:, touched, None], su, 0.0)
            none_s = chow_rss(pre[touched], su, sQ, wt[:, touched])["none"]
            swap_cost[k] = 0.5 * (none_s - rss["none"][touched]).sum() + prior

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
        jump = float(np.median(np.maximum(rss["child_size"], rss["parent_size"])[touched]))
        return Attribution("swap", a, b, [(a, float(post[best])), (b, float(post[best]))],
                           float(post[best]), touched.tolist(), jump, evidence)
    s = best
    mine = np.flatnonzero(inc_c[s] | inc_p[s])
    ready_mine = mine[use[mine]]
    size = np.where(inc_c[s, ready_mine], rss["child_size"][ready_mine], rss["parent_size"][ready_mine])
    if np.median(size) < min_jump:
        return Attribution(None, evidence=evidence)
    order = np.argsort(-post[:m])
    cands = [(int(k), float(post[k])) for k in order if post[k] >= CANDIDATE_SHARE]
    return Attribution("slip", s, -1, cands, float(post[s]), mine.tolist(), float(np.median(size)), evidence)
