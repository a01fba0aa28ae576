"""Which sensor slipped (or which two swapped), from the window around a suspected change.

Every hypothesis is scored by how well it explains the residuals of the joints near the change over
the window (8 s before the onset and the frames since), each joint's residual fitted as a smooth
function of the configuration (`baseline`): "sensor s slipped" = its placement moved at the
onset by one vector (of at least the minimum jump) in its own frame, which every joint of s shows and
no other joint does; "a and b swapped" = exchanging their data from the onset on brings every joint
back to what the frames before predict; "nothing" = the smooth fit explains every joint before and
after (soft tissue, new motion, a fit still settling). Scores are Gaussian log-likelihoods in each
frame's own noise (plus a BIC term per fitted step), so the posterior over hypotheses gives the
confidence and, for a body whose joints cannot tell two sensors apart, both candidates.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from itertools import combinations

import numpy as np

from flockcal.solver.slippage.baseline import configuration_design, prediction_rss, step_fits, step_scan
from flockcal.solver.slippage.stats import present, residual, touching

# Other sensors are listed as candidates down to this posterior share.
CANDIDATE_SHARE = 0.05
# A neighbouring joint's rotation moves the skin under a sensor by about a centimetre per right angle:
# the prior sd of those regressors' coefficients, metres per unit of a rotation-matrix entry, so that
# directions a window hardly turns along stay near zero instead of fitting noise (and the step). The
# joint's own rotation has none: a first swing to the end of a range must be free to follow the skin.
NEIGHBOUR_PRIOR_M = 0.01
OWN_COLUMNS = 11  # 1, the trend and the nine entries of the joint's own rotation


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
    step: np.ndarray | None = None  # slip: the fitted step (3,) in the sensor's own frame, metres
    later_row: int | None = None  # a later window row the (likeliest) sensor's step starts at, much likelier than the onset
    steps: np.ndarray | None = None  # slip: every sensor's fitted step (m, 3) in its own frame, metres


@dataclass
class Window:
    """The frames around a suspected change, as the monitor hands them over (L frames, P joints).

    g, Q: cached joint geometry (`stats.joint_geometry`); use (L, P): frames each joint may
    use (valid, in its current segment); weight (L, P) = 1/σ²; times (L,); onset_row: first row of the
    change; c, l (P, 3): the estimates; swapped(perm, joints) -> (g, Q) of the frames from the onset on
    with the sensors' data permuted, for those joints; swap_plausible(a, b): whether exchanging a's and
    b's data at the onset makes their paths more continuous, not less (else the swap is not scored);
    weight_joined (L, P): the weights "sensor s slipped" is scored with where s is seen through two or
    more of the fitted joints (None: `weight`).
    """

    times: np.ndarray
    g: np.ndarray
    Q: np.ndarray
    use: np.ndarray
    weight: np.ndarray
    onset_row: int
    c: np.ndarray
    l: np.ndarray
    swapped: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None
    swap_plausible: Callable[[int, int], bool] | None = None
    weight_joined: np.ndarray | None = None


def attribute(win: Window, joints: np.ndarray, nbrs: np.ndarray, ready: np.ndarray,
              suspects: np.ndarray, n_sensors: int, min_jump: float, min_evidence: float,
              late_rows: int = 0, min_tail: int = 4, more_looks: bool = False,
              reseat_refuted: bool = False) -> Attribution:
    """Score slip and swap hypotheses around the change (see module docstring).

    joints (P, 2) (child, parent); nbrs (P, width): `baseline.neighbours(joints)`; ready (P,)
    joints with a baseline; suspects (P,) joints whose step test fired. Only joints sharing a sensor
    with a suspect are fitted: a sensor none of whose joints fired cannot be the one that slipped.
    `late_rows` > 0: also look for the slipped sensor's step starting at every later row (up to
    `min_tail` rows before the end); one starting more than `late_rows` after the onset and likelier
    than the onset's by more than the search costs is reported as `later_row` (the suspicion's onset
    belongs to something else, soft tissue before the slip, and the slip to that later start). With
    `reseat_refuted`, when no hypothesis wins, the likeliest sensor's later starts are searched too, once
    the suspicion is to be dropped (not while `more_looks` remains and a step is likelier than not).
    """
    P = len(joints)
    after = np.arange(len(win.times)) >= win.onset_row
    sensors = present(joints[suspects])
    near = touching(joints, sensors) & ready & (win.use & after[:, None]).any(axis=0)
    sel = np.flatnonzero(near)
    if not (near & suspects).any():
        return Attribution(None)
    c, l = win.c[sel], win.l[sel]
    Q = win.Q[:, sel]
    x = residual(win.g[:, sel], Q, c, l)
    y = (Q.swapaxes(-1, -2) @ x[..., None])[..., 0]
    w = np.where(win.use[:, sel], win.weight[:, sel], 0.0)
    none = np.zeros((P, 0), dtype=np.intp)
    D = configuration_design(win.Q, None, win.times, win.onset_row, sel, none, full=nbrs)
    m = n_sensors
    inc_c = joints[:, 0][None, :] == np.arange(m)[:, None]  # (m, P) sensor is the joint's child
    inc_p = joints[:, 1][None, :] == np.arange(m)[:, None]
    slip_cost, steps, fx = _slip_costs(D, x, y, w, after, sel, inc_c, inc_p, min_jump)
    # Only a sensor one of whose joints stepped can have slipped (its other joints may lag behind).
    possible = np.zeros(m, dtype=bool)
    possible[sensors] = True
    possible &= ((inc_c | inc_p) & near[None, :]).any(axis=1)
    joined = np.zeros(m, dtype=bool)
    wj = w
    if win.weight_joined is not None:
        # A sensor seen through two or more joints: one step in its own frame must explain all of them,
        # which skin in a new pose does not mimic, so its score counts no more noise than the frames show.
        wj = np.where(win.use[:, sel], win.weight_joined[:, sel], 0.0)
        cost_j, steps_j, _ = _slip_costs(D, x, y, wj, after, sel, inc_c, inc_p, min_jump)
        joined = ((inc_c | inc_p) & near[None, :]).sum(axis=1) >= 2
        # ... unless, with those weights, a leaf beside it explains the step better: a hand's slip shows
        # on the wrist, which the forearm shares; the leaf's own score then decides, as before.
        leaf_best = np.min(np.where(possible & ~joined, cost_j, np.inf), initial=np.inf)
        joined &= cost_j <= leaf_best
        slip_cost = np.where(joined, cost_j, slip_cost)
        steps = np.where(joined[:, None], steps_j, steps)
    size = np.linalg.norm(steps, axis=1)
    slip_cost = np.where(possible, slip_cost, np.inf)

    # Swaps: only among sensors of the joints that fired. Exchanging their data from the onset on must
    # bring every joint back to what the frames before the onset predict (judged by prediction: a fit
    # across the onset could follow the jump that exchanging two bodies' rotations puts in its regressors).
    swaps = [pair for pair in combinations(sensors.tolist(), 2) if win.swap_plausible is None or win.swap_plausible(*pair)]
    swap_cost = np.full(len(swaps), np.inf)
    if swaps and win.swapped is not None:
        prior = np.log(len(swaps))
        stay = np.zeros(P)
        stay[sel] = prediction_rss(D, x, w, after)
        for k, (a, b) in enumerate(swaps):
            perm = np.arange(m)
            perm[[a, b]] = [b, a]
            touched = sel[touching(joints[sel], (a, b))]
            if not len(touched):
                continue
            g2, Q2 = win.swapped(perm, touched)
            g_all, Q_all = win.g.copy(), win.Q.copy()
            g_all[win.onset_row:, touched], Q_all[win.onset_row:, touched] = g2, Q2
            Qs = Q_all[:, touched]
            xs = residual(g_all[:, touched], Qs, win.c[touched], win.l[touched])
            Ds = configuration_design(Q_all, None, win.times, win.onset_row, touched, none, full=nbrs)
            ws = np.where(win.use[:, touched], win.weight[:, touched], 0.0)
            swap_cost[k] = 0.5 * (prediction_rss(Ds, xs, ws, after) - stay[touched]).sum() + prior

    costs = np.concatenate([slip_cost, swap_cost])
    best = int(np.argmin(costs))
    evidence = -float(costs[best])
    if not np.isfinite(evidence) or evidence < min_evidence:
        later = None
        if reseat_refuted and late_rows > 0 and np.isfinite(slip_cost).any() and not (more_looks and evidence > 0):
            # Refuted at this onset: a slip that landed a moment after it (in a pose the baseline has not
            # seen, where soft tissue raised the suspicion first) may still be a step from a later start.
            s = int(np.argmin(slip_cost))
            ws = wj if win.weight_joined is not None and joined[s] else w
            later = _later_start(D, x, y, ws, sel, inc_c[s], inc_p[s], win.onset_row, late_rows, min_tail,
                                 min_jump=min_jump)
        return Attribution(None, evidence=evidence, later_row=later)
    post = np.exp(-(costs - costs[best]))
    post /= post.sum()
    if best >= m:
        a, b = swaps[best - m]
        touched = np.flatnonzero(touching(joints, (a, b)))
        jump = float(np.median(np.linalg.norm(fx.step, axis=1)))
        return Attribution("swap", a, b, [(a, float(post[best])), (b, float(post[best]))],
                           float(post[best]), touched.tolist(), jump, evidence)
    s = best
    mine = np.flatnonzero(inc_c[s] | inc_p[s])
    if size[s] < min_jump:
        return Attribution(None, evidence=evidence)
    order = np.argsort(-post[:m])
    cands = [(int(k), float(post[k])) for k in order if post[k] >= CANDIDATE_SHARE]
    ws = wj if joined[s] else w
    later = _later_start(D, x, y, ws, sel, inc_c[s], inc_p[s], win.onset_row, late_rows, min_tail) if late_rows > 0 else None
    return Attribution("slip", s, -1, cands, float(post[s]), mine.tolist(), float(size[s]), evidence, steps[s], later,
                       steps)


def _later_start(D, x, y, w, sel, child, parent, onset_row: int, late_rows: int, min_tail: int,
                 min_jump: float = 0.0) -> int | None:
    """The row a sensor's step most likely starts at, from the onset on, if more than `late_rows`
    after the onset and likelier than a step from the onset by more than log(rows searched) nats; with
    `min_jump` > 0 (a suspicion nothing explained at its onset) only a step of at least that size, more
    likely than none (nats, with `_slip_costs`' cost of its frames), is worth another test.

    A suspicion raised by soft tissue and kept for another look can have a slip land inside its window
    a moment later: a step from the suspicion's onset then explains part of it, on the joints that
    fired, and can name the wrong sensor (a leaf beside the one that slipped). The sensor's joints
    combine as in `_slip_costs`: +δ where it is the child, −δ where it is the parent."""
    L = len(x)
    starts = np.arange(onset_row, L - min_tail)
    own = (child | parent)[sel]
    if len(starts) < 2 or not own.any():
        return None
    k = np.flatnonzero(own)
    g, h = step_scan(D[:, k], [x[:, k], y[:, k]], w[:, k], starts, prior_sd=NEIGHBOUR_PRIOR_M, prior_from=OWN_COLUMNS)
    sign_c, sign_p = child[sel][k].astype(float), parent[sel][k].astype(float)
    G = (sign_c[None, :, None] * g[:, :, 0] - sign_p[None, :, None] * g[:, :, 1]).sum(axis=1)  # (n, 3)
    H = ((sign_c + sign_p)[None, :] * h).sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        reduction = np.nan_to_num((G * G).sum(axis=1) / H)
    best = int(np.argmax(reduction))
    if not (best > late_rows and 0.5 * (reduction[best] - reduction[0]) > np.log(len(starts))):
        return None
    if min_jump > 0:
        with np.errstate(invalid="ignore", divide="ignore"):
            size = float(np.linalg.norm(np.nan_to_num(G[best] / H[best])))
        frames = max((L - starts[best]) * len(k), 1)
        if size < min_jump or 0.5 * reduction[best] - 1.5 * np.log(frames) <= 0:
            return None
    return int(starts[best])


def _slip_costs(D, x, y, w, after, sel, inc_c, inc_p, min_jump):
    """(m,) cost of "sensor s slipped" against "nothing" (negative: evidence for it), each sensor's
    step (m, 3) in its own frame, and the child-frame fits, with regressors D for the selected joints.

    Its placement moved by one vector δ in its own frame, so each of its joints steps by that vector:
    by +δ in the child-frame series where s is the child (u = c + R_iᵀ(t_i − t_j) − Q l gains
    R_iᵀ R_i δ), by −δ in the parent-frame series where it is the parent. The joints' step terms add
    up into one fit of δ."""
    fx, fy = step_fits(D, [x, y], w, after, prior_sd=NEIGHBOUR_PRIOR_M, prior_from=OWN_COLUMNS)
    P = inc_c.shape[1]
    gx, gy, hx = np.zeros((P, 3)), np.zeros((P, 3)), np.zeros(P)
    gx[sel], gy[sel], hx[sel] = fx.g, fy.g, fx.h
    n_after, w_after = np.zeros(P), np.zeros(P)
    n_after[sel], w_after[sel] = fx.after, fx.weight_after
    ic, ip = inc_c.astype(float), inc_p.astype(float)
    G = ic @ gx - ip @ gy  # (m, 3)
    Hs = (ic + ip) @ hx
    with np.errstate(invalid="ignore", divide="ignore"):
        step = np.nan_to_num(G / Hs[:, None])
        reduction = np.nan_to_num((G * G).sum(axis=1) / Hs)
    short = np.maximum(min_jump - np.linalg.norm(step, axis=1), 0.0)
    cost = (-0.5 * reduction + 1.5 * np.log(np.maximum((ic + ip) @ n_after, 1))
            + 0.5 * ((ic + ip) @ w_after) * short**2)
    return cost, step, fx
