"""A step at the frame rate, in the slipped sensor's own frame: the evidence for "sensor s slipped at frame k"
from the ±`half` frames around k alone, each joint residual of s modelled as a cubic in time plus a linear
function of the joint's own rotation, plus one step vector shared by every joint of s (a slip moves them all
by the same vector in s's frame; skin slides smoothly with the joint angles, so over a few tenths of a
second it is one of those smooth terms, not a step). No baseline from seconds before is used, so a pose
never seen before is no harder than any other. Pure numpy over (onsets, joints, axes)."""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

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
    h = (np.arange(2 * half) >= half).astype(float)
    B = _poly_basis(half, degree)
    return h - B @ (B.T @ h)


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


def incidence(joints: np.ndarray, m: int) -> tuple[np.ndarray, np.ndarray]:
    """Each sensor's joints, padded: (m, D) joint indices (-1: none) and (m, D) roles (0: the sensor is the
    joint's child, 1: its parent), D the most joints any sensor has."""
    J = np.asarray(joints, dtype=int).reshape(-1, 2)
    return _incidence(J.tobytes(), len(J), int(m))


@lru_cache(maxsize=16)
def _incidence(key: bytes, p: int, m: int) -> tuple[np.ndarray, np.ndarray]:
    J = np.frombuffer(key, dtype=int).reshape(p, 2)
    D = max(1, int(np.bincount(J.ravel(), minlength=m).max())) if len(J) else 1
    idx = np.full((m, D), -1)
    role = np.zeros((m, D), dtype=int)
    fill = np.zeros(m, dtype=int)
    for j, pair in enumerate(J.tolist()):
        for r, s in enumerate(pair):
            idx[s, fill[s]], role[s, fill[s]] = j, r
            fill[s] += 1
    idx.flags.writeable = role.flags.writeable = False  # shared by every call with these joints
    return idx, role


@lru_cache(maxsize=4)
def _poly_basis(half: int, degree: int = 3) -> np.ndarray:
    """An orthonormal basis (2·half, degree + 1) of the polynomials in time over a window of 2·half frames."""
    tau = (np.arange(2 * half) - half + 0.5) / half
    basis = np.linalg.qr(np.vander(tau, degree + 1, increasing=True))[0]
    basis.flags.writeable = False
    return basis


def _halves(e: np.ndarray, half: int, k: int) -> np.ndarray:
    """Of the k windows of 2·half − 2 second differences e (n−2, …), the larger of the two halves' means
    (each half − 2 long, the two in the middle that a step itself shows left out), per axis (÷ 18)."""
    C = np.concatenate([np.zeros((1,) + e.shape[1:]), np.cumsum(e, axis=0)])
    m = half - 2
    first = C[m:m + k] - C[:k]
    second = C[half + m:half + m + k] - C[half:half + k]
    return np.maximum(first, second) / (m * 18.0)


def frame_steps(g, Q, pv, c, l, joints: np.ndarray, sensors, ready: np.ndarray, lo: int, hi: int, half: int,
                floor_m: float, contrast: np.ndarray, t: np.ndarray | None = None,
                law: tuple[np.ndarray, np.ndarray] | None = None) -> list[FrameStep]:
    """Best frame step of each sensor in `sensors`, onsets from row lo to row hi (exclusive) of the frames
    g (L, P, 3), Q (L, P, 3, 3), pv (L, P) (rows, not global indices); its joints are the ready ones it is
    child or parent of. Returns one FrameStep per sensor with at least one such joint (onset as a row).
    With positions t (L, m, 3) and each joint's `noise_law` (a, b), a window's noise is at least what the law
    gives for the frames the step estimate leans on. Every joint's windows are worked out once, in both its
    child's and its parent's frame, and each sensor gathers its own."""
    joints = np.asarray(joints)
    L, P = len(g), len(joints)
    lo, hi = max(lo, half), min(hi, L - half + 1)
    sensors = np.asarray(list(sensors), dtype=int)
    if hi <= lo or not len(sensors) or not P:
        return []
    m = int(max(joints.max(), sensors.max())) + 1
    idx, role = incidence(joints, m)
    idx, role = idx[sensors], role[sensors]
    use = (idx >= 0) & ready[np.maximum(idx, 0)]  # (s, D): the ready joints of each sensor
    nj = use.sum(axis=1)
    if not nj.any():
        return []
    rows = slice(lo - half, hi + half - 1)
    k, n2 = hi - lo, 2 * half
    hh0 = float(contrast @ contrast)
    basis = _poly_basis(half)  # (2h, 4) orthonormal: the cubics
    ridge = 1e-6 * n2  # per rotation entry, in its own units (1 = a right angle's swing)
    gr, Qr = g[rows], Q[rows]
    n = len(gr)
    u = residual(gr, Qr, c, l)  # (n, P, 3) child frame
    # In the parent's frame the residual is Qᵀu, and a slip of the parent moves it by −d.
    x = np.stack([u, -(Qr.swapaxes(-1, -2) @ u[..., None])[..., 0]], axis=2)  # (n, P, 2, 3)
    # Each window's step contrast also has the joint's own relative rotation projected out: a joint centre a
    # little off, or skin that slides with the joint's angle, is linear in its nine entries and turns fast
    # with a fast limb, where a cubic in time over a few tenths of a second is not enough. (The rotation
    # columns are not centred: the cubic's constant column projects that out of everything below anyway.)
    qw = np.lib.stride_tricks.sliding_window_view(Qr.reshape(n, P, 9), n2, axis=0)  # (k, P, 9, 2h)
    hq = qw @ contrast  # (k, P, 9): the poly-free step against each rotation entry (contrast ⟂ the cubic)
    A = qw @ basis  # (k, P, 9, 4)
    # The rotation columns projected off the cubic, qp = qw − (qw B) Bᵀ, enter only through qp qpᵀ and
    # coefᵀ qp (ridge: entries that hardly change in a window carry no information and must not blow up).
    G = qw @ qw.swapaxes(-1, -2) - A @ A.swapaxes(-1, -2) + ridge * np.eye(9)
    coef = np.linalg.solve(G, hq[..., None])  # (k, P, 9, 1)
    ct = coef.swapaxes(-1, -2)
    wt = contrast - (ct @ qw)[..., 0, :] + (ct @ A)[..., 0, :] @ basis.T  # (k, P, 2h): what b takes of each frame
    win = np.lib.stride_tricks.sliding_window_view(x.reshape(n, P, 6), n2, axis=0)  # (k, P, 6, 2h)
    b = (win @ wt[..., None])[..., 0].reshape(k, P, 2, 3)
    hh = np.maximum(hh0 - (hq * coef[..., 0]).sum(axis=-1), 1e-3 * hh0)  # (k, P)
    dd = x[2:] - 2 * x[1:-1] + x[:-2]  # (n-2, P, 2, 3) second differences
    # Tracker noise grows with speed, and a limb can speed up several-fold inside one window: each half's
    # own level, the larger counted for the whole (a step seen against the quieter half alone is noise).
    # Means, not medians, and the two second differences the step itself shows in left out.
    var = np.maximum(_halves((dd * dd).sum(axis=-1), half, k), floor_m**2)  # (k, P, 2) each joint's whole noise
    if law is not None:
        # The step estimate leans on the frames around its onset, where a limb is often fastest and the
        # tracker noisiest; a window's second differences see too few of those frames to measure it (the
        # walk hour's false alarm, docs/slippage.md): the noise the whole buffer's law gives for the frames
        # the estimate weighs, when that is more.
        w2 = wt * wt
        sw = np.lib.stride_tricks.sliding_window_view(speed_proxy(t[rows], joints), n2, axis=0)  # (k, P, 2h)
        var = np.maximum(var, (law[0] + law[1] * (w2 * sw).sum(axis=-1) / w2.sum(axis=-1))[..., None])
    okw = np.lib.stride_tricks.sliding_window_view(pv[rows], n2, axis=0).all(axis=-1)  # (k, P)
    # Each sensor's joints, in its own frame: (k, s, D, …), padded slots masked by `use`.
    ji = np.maximum(idx, 0)
    bs, vs, hs = b[:, ji, role], var[:, ji, role], hh[:, ji]
    oks = okw[:, ji] | ~use
    # The sensor's own noise is common to all its joints (in its frame): the products of two joints' second
    # differences measure it, E[Δ²x_j · Δ²x_k] = 18 σ_s² per axis.
    dds = dd[:, ji, role] * use[..., None]  # (n-2, s, D, 3)
    sumd = dds.sum(axis=2)
    cross = ((sumd * sumd).sum(axis=-1) - (dds * dds).sum(axis=(2, 3))) / np.maximum(nj * (nj - 1), 1)
    vmin = np.where(use, vs, np.inf).min(axis=2)  # (k, s)
    common = np.where(nj == 1, vmin, np.clip(_halves(cross, half, k), 0.0, 0.95 * vmin))
    other = np.maximum(vs - common[..., None], 1e-6 * vs)  # (k, s, D) the other sensors' share
    # Each joint's own step estimate d_j = b_j / hh_j has covariance σ_s²/hh̄ + δ_jk σ_oj²/hh_j between
    # joints; the shared step is their generalised least-squares mean (Sherman-Morrison).
    dj = bs / hs[..., None]
    inv = np.where(use & oks, hs / other, 0.0)
    a = common / (np.where(use, hs, 0.0).sum(axis=2) / np.maximum(nj, 1))
    S = inv.sum(axis=2)
    with np.errstate(invalid="ignore", divide="ignore"):
        d = (inv[..., None] * dj).sum(axis=2) / S[..., None]  # (k, s, 3)
        shared = 0.5 * (d * d).sum(axis=-1) / (a + 1.0 / S)
        disagree = 0.5 * (inv * ((dj - d[:, :, None]) ** 2).sum(axis=-1)).sum(axis=2)
    # One joint is its own shared step: its disagreement is nil, not the round-off of d_j − d (times a weight
    # of 1e6/σ²), which came out above the gate's 0 at about half the onsets and lost them.
    disagree = np.where(nj == 1, 0.0, disagree)
    # A step only some of the sensor's joints show is a neighbour's slip, or skin: beyond the χ² scatter of
    # one shared vector (3 degrees of freedom per further joint), the sensor is not the one that moved.
    ok = oks.all(axis=2) & (nj > 0) & (disagree <= DISAGREE_PER_JOINT * (nj - 1))
    score = np.where(ok, shared - disagree, -np.inf)
    best = np.argmax(score, axis=0)  # (s,)
    out = []
    for i in np.flatnonzero(np.isfinite(score[best, np.arange(len(sensors))])):
        kb = int(best[i])
        out.append(FrameStep(int(sensors[i]), lo + kb, float(score[kb, i]), float(shared[kb, i]),
                             float(disagree[kb, i]), d[kb, i].copy(), idx[i][use[i]]))
    return out
