"""A step at the frame rate, in the slipped sensor's own frame: the evidence for "sensor s slipped at frame k"
from the ±`half` frames around k alone, each joint residual of s modelled as a cubic in time plus a linear
function of the joint's own rotation, plus one step vector shared by every joint of s (a slip moves them all
by the same vector in s's frame; skin slides smoothly with the joint angles, so over a few tenths of a
second it is one of those smooth terms, not a step). No baseline from seconds before is used, so a pose
never seen before is no harder than any other. Pure numpy over (onsets, joints, axes)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flockcal.solver.slippage.stats import residual


# Nats of disagreement with one shared step allowed per joint beyond the first (a χ² with 3 degrees of
# freedom exceeds 12 in 0.7 % of cases).
DISAGREE_PER_JOINT = 6.0
# Below any tracker's noise (0.1 mm per axis): where the noise law's weights stop growing.
VAR_FLOOR_M2 = 1e-8


@dataclass
class FrameStep:
    sensor: int
    onset: int  # global frame index of the first frame after the step
    score: float  # nats: the shared step's evidence, less the joints' disagreement with it
    evidence: float  # nats of the shared step, noise counted as fully shared between the joints
    disagreement: float  # nats: what each joint's own step explains beyond the shared one
    step: np.ndarray  # (3,) metres in the sensor's own frame
    joints: np.ndarray  # the joints of the sensor that were scored


def step_contrast(half: int, degree: int = 3) -> np.ndarray:
    """The step indicator over 2·half frames (0 before frame `half`, 1 from it), with the polynomial of
    `degree` in time projected out: its inner product with a window is that window's step evidence."""
    tau = (np.arange(2 * half) - half + 0.5) / half
    B = np.vander(tau, degree + 1, increasing=True)
    h = (tau > 0).astype(float)
    return h - B @ np.linalg.lstsq(B, h, rcond=None)[0]


def speed_proxy(t: np.ndarray, joints: np.ndarray) -> np.ndarray:
    """Each joint's speed term per frame (n, P): the squared displacement of its two sensors over 4 frames,
    summed (m² per 4 frames; central, held at the ends), from positions t (n, m, 3)."""
    d = np.zeros_like(t)
    if len(t) > 4:
        d[2:-2] = t[4:] - t[:-4]
        d[:2], d[-2:] = d[2], d[-3]
    s = (d * d).sum(axis=-1)
    return s[:, joints[:, 0]] + s[:, joints[:, 1]]


def noise_law(g, Q, t, pv, c, l, joints: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each joint's noise as its speed makes it, var = a + b·s per axis (s: `speed_proxy`), fitted by
    weighted least squares to the squared second differences of its residual over the frames given (a, b ≥ 0;
    (P,) each). A tracker whose error does not grow with speed gets b ≈ 0 and its plain level in a."""
    u = residual(g, Q, c, l)
    dd = u[2:] - 2 * u[1:-1] + u[:-2]
    e = (dd * dd).sum(axis=-1) / 18.0  # per axis: E‖Δ²x‖² = 18σ² for white noise
    ok = (pv[2:] & pv[1:-1] & pv[:-2]).astype(float)
    s = speed_proxy(t, joints)[1:-1]
    w = ok
    for _ in range(3):
        S1, Ss, Sss = w.sum(axis=0), (w * s).sum(axis=0), (w * s * s).sum(axis=0)
        Se, Ses = (w * e).sum(axis=0), (w * e * s).sum(axis=0)
        den = Sss * S1 - Ss * Ss
        b = np.maximum(np.where(den > 0, (Ses * S1 - Ss * Se) / np.where(den > 0, den, 1.0), 0.0), 0.0)
        a = np.maximum((Se - b * Ss) / np.where(S1 > 0, S1, 1.0), 0.0)
        # A squared difference scatters as its mean squared: weigh each frame by the fit's variance² so that
        # the fast frames' scatter does not decide the slow frames' level (two reweightings suffice).
        w = ok / np.maximum(a + b * s, VAR_FLOOR_M2) ** 2
        w /= np.maximum(w.max(axis=0), 1e-300)
    return a, b


def frame_steps(g, Q, pv, c, l, joints: np.ndarray, sensors, ready: np.ndarray, lo: int, hi: int, half: int,
                floor_m: float, contrast: np.ndarray, t: np.ndarray | None = None,
                law: tuple[np.ndarray, np.ndarray] | None = None) -> list[FrameStep]:
    """Best frame step of each sensor in `sensors`, onsets from row lo to row hi (exclusive) of the frames
    g (L, P, 3), Q (L, P, 3, 3), pv (L, P) (rows, not global indices); its joints are the ready ones it is
    child or parent of. Returns one FrameStep per sensor with at least one such joint (onset as a row).
    With positions t (L, m, 3) and each joint's `noise_law` (a, b), a window's noise is at least what the law
    gives for the frames the step estimate leans on."""
    out = []
    L = len(g)
    lo, hi = max(lo, half), min(hi, L - half + 1)
    if hi <= lo:
        return out
    rows = slice(lo - half, hi + half - 1)
    hh0 = float(contrast @ contrast)
    tau = (np.arange(2 * half) - half + 0.5) / half
    basis, _ = np.linalg.qr(np.vander(tau, 4, increasing=True))  # (2h, 4) orthonormal
    basis_t = basis.T
    ridge = 1e-6 * 2 * half  # per rotation entry, in its own units (1 = a right angle's swing)
    speed = None if law is None else speed_proxy(t[rows], joints)  # (n, P), once for every sensor's joints
    for s in sensors:
        child = (joints[:, 0] == s) & ready
        parent = (joints[:, 1] == s) & ready
        js = np.flatnonzero(child | parent)
        if not len(js):
            continue
        u = residual(g[rows][:, js], Q[rows][:, js], c[js], l[js])  # (n, j, 3) child frame
        # In the parent's frame the residual is Qᵀu, and a slip of the parent moves it by −d.
        up = -(Q[rows][:, js].swapaxes(-1, -2) @ u[..., None])[..., 0]
        x = np.where(child[js][None, :, None], u, up)
        ok = pv[rows][:, js]
        win = np.lib.stride_tricks.sliding_window_view(x, 2 * half, axis=0)  # (k, j, 3, 2h)
        okw = np.lib.stride_tricks.sliding_window_view(ok, 2 * half, axis=0).all(axis=-1)  # (k, j)
        # Each window's step contrast also has the joint's own relative rotation projected out: a joint
        # centre a little off, or skin that slides with the joint's angle, is linear in its nine entries
        # and turns fast with a fast limb, where a cubic in time over a few tenths of a second is not enough.
        q = Q[rows][:, js].reshape(-1, len(js), 9)
        qw = np.lib.stride_tricks.sliding_window_view(q, 2 * half, axis=0)  # (k, j, 9, 2h)
        qw = qw - qw.mean(axis=-1, keepdims=True)
        hq = qw @ contrast  # (k, j, 9): the poly-free step against each rotation entry (contrast ⟂ constants)
        # Project the rotation columns off the polynomial as well, then the contrast off them (ridge: entries
        # that hardly change in a window carry no information and must not blow up).
        qp = qw - (qw @ basis) @ basis_t  # (k, j, 9, 2h) with basis orthonormal over the window
        G = qp @ qp.swapaxes(-1, -2) + ridge * np.eye(9)
        coef = np.linalg.solve(G, hq[..., None])[..., 0]  # (k, j, 9)
        b_poly = win @ contrast  # (k, j, 3)
        xq = win @ qp.swapaxes(-1, -2)  # (k, j, 3, 9)
        b = b_poly - (xq @ coef[..., None])[..., 0]
        hh = hh0 - (hq * coef).sum(axis=-1)  # (k, j)
        hh = np.maximum(hh, 1e-3 * hh0)
        dd = x[2:] - 2 * x[1:-1] + x[:-2]  # (n-2, j, 3) second differences
        d2 = (dd * dd).sum(axis=-1)  # (n-2, j)
        # The sensor's own noise is common to all its joints (in its frame): the products of two joints'
        # second differences measure it, E[Δ²x_j · Δ²x_k] = 18 σ_s² per axis.
        nj = len(js)
        sumd = dd.sum(axis=1)
        cross = ((sumd * sumd).sum(axis=-1) - d2.sum(axis=1)) / max(nj * (nj - 1), 1)  # (n-2,)
        both = np.concatenate([d2, cross[:, None]], axis=1)
        bw = np.lib.stride_tricks.sliding_window_view(both, 2 * half - 2, axis=0)[: len(b)]  # (k, j+1, 2h-2)
        # Tracker noise grows with speed, and a limb can speed up several-fold inside one window: each half's
        # own level, the larger counted for the whole (a step seen against the quieter half alone is noise).
        # Means, not medians, and the two second differences the step itself shows in left out.
        level = np.maximum(bw[..., : half - 2].mean(axis=-1), bw[..., half:].mean(axis=-1)) / 18.0  # per axis
        var = np.maximum(level[:, :nj], floor_m**2)  # (k, j) each joint's whole noise
        if law is not None:
            # The step estimate leans on the frames around its onset, where a limb is often fastest and the
            # tracker noisiest; a window's second differences see too few of those frames to measure it (the
            # walk hour's false alarm, docs/slippage.md): the noise the whole buffer's law gives for the frames
            # the estimate weighs, when that is more.
            wt = contrast - (coef[..., None] * qp).sum(axis=-2)  # (k, j, 2h): what b takes of each frame
            wt *= wt
            sw = np.lib.stride_tricks.sliding_window_view(speed[:, js], 2 * half, axis=0)
            at = law[0][js] + law[1][js] * (wt * sw[: len(b)]).sum(axis=-1) / wt.sum(axis=-1)
            var = np.maximum(var, at)
        common = var.min(axis=1) if nj == 1 else np.clip(level[:, nj], 0.0, 0.95 * var.min(axis=1))  # (k,)
        other = np.maximum(var - common[:, None], 1e-6 * var)  # (k, j) the other sensors' share
        # Each joint's own step estimate d_j = b_j / hh_j has covariance σ_s²/hh̄ + δ_jk σ_oj²/hh_j between
        # joints; the shared step is their generalised least-squares mean (Sherman-Morrison).
        dj = b / hh[..., None]
        Dj = np.where(okw, other / hh, np.inf)
        a = common / hh.mean(axis=1)
        inv = 1.0 / Dj
        S = inv.sum(axis=1)
        full = okw.all(axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            d = (inv[..., None] * dj).sum(axis=1) / S[:, None]
            shared = 0.5 * (d * d).sum(axis=-1) / (a + 1.0 / S)
            disagree = 0.5 * (inv * ((dj - d[:, None]) ** 2).sum(axis=-1)).sum(axis=1)
        if nj == 1:
            # One joint is its own shared step: its disagreement is nil, not the round-off of d_j − d (times
            # a weight of 1e6/σ²), which came out above the gate's 0 at about half the onsets and lost them.
            disagree = np.zeros_like(shared)
        # A step only some of the sensor's joints show is a neighbour's slip, or skin: beyond the χ² scatter of
        # one shared vector (3 degrees of freedom per further joint), the sensor is not the one that moved.
        score = np.where(full & (disagree <= DISAGREE_PER_JOINT * (nj - 1)), shared - disagree, -np.inf)
        k = int(np.argmax(score))
        if not np.isfinite(score[k]):
            continue
        out.append(FrameStep(int(s), lo + k, float(score[k]), float(shared[k]), float(disagree[k]), d[k].copy(),
                             js))
    return out
