"""Best rigid transforms between point clouds with gaps (weighted Kabsch), vectorised over frames.

Every optical step that needs a pose (initial guesses, skeleton projection, body rotations) goes
through `rigid_fit`; NaN points simply carry no weight.
"""

from __future__ import annotations

import numpy as np


def rigid_fit(reference: np.ndarray, observed: np.ndarray, min_points: int = 3):
    """Rotation R (n,3,3), translation t (n,3) and ok (n,) with observed ≈ R @ reference + t.

    reference (q, 3) or (n, q, 3) points in the body frame; observed (n, q, 3) world points, NaN
    where unseen. A frame is ok when at least `min_points` points are seen in both and they do not
    lie on one line (then the rotation about that line would be arbitrary).
    """
    obs = np.asarray(observed, dtype=float)
    ref = np.broadcast_to(np.asarray(reference, dtype=float), obs.shape)
    w = (np.isfinite(obs).all(-1) & np.isfinite(ref).all(-1)).astype(float)  # (n, q)
    count = w.sum(-1)
    safe = np.maximum(count, 1.0)[:, None]
    X = np.where(w[..., None] > 0, obs, 0.0)
    P = np.where(w[..., None] > 0, ref, 0.0)
    xc = (w[..., None] * X).sum(1) / safe
    pc = (w[..., None] * P).sum(1) / safe
    Xd = (X - xc[:, None]) * w[..., None]
    Pd = (P - pc[:, None]) * w[..., None]
    # Batched matmul, not einsum: einsum does not reach BLAS for these shapes and was most of the cost.
    H = Pd.transpose(0, 2, 1) @ Xd
    # (|P|² + |X|²)/2 bounds the fit's score from above and is near it when the fit is good: Newton starts there.
    bound = 0.5 * ((Pd * Pd).sum((1, 2)) + (Xd * Xd).sum((1, 2)))
    R, fast = _horn(H, bound, count >= min_points)
    ok = count >= min_points
    slow = ~fast
    if slow.any():
        # Too few points, (nearly) collinear or an ill-separated eigenvalue: the SVD, as before, for those frames.
        R[slow], S = _kabsch_svd(H[slow])
        # Collinear points leave the second singular value at noise level: the rotation about the line is free.
        ok[slow] &= (S[:, 1] > 1e-6 * np.maximum(S[:, 0], 1e-300)) & (S[:, 0] > 0)
    t = xc - (R @ pc[..., None])[..., 0]
    return R, t, ok


def _kabsch_svd(H: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotations R (n,3,3) maximising tr(R H) (Kabsch: V diag(1,1,d) Uᵀ) and H's singular values (n,3)."""
    U, S, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(U @ Vt))
    d[d == 0] = 1.0
    D = np.ones((len(H), 3))
    D[:, 2] = d
    return (Vt.transpose(0, 2, 1) * D[:, None, :]) @ U.transpose(0, 2, 1), S


# Horn's quaternion method, vectorised with plain ufuncs: a batched LAPACK SVD of 3x3 matrices costs ~2 µs a
# matrix and was the largest cost of fit-markers on the pyomeca file after start-up (268 calls). Horn's 4x4
# matrix N is linear in H (N.flat = H.flat @ _HORN); the rotation is linear in the outer product of its unit
# quaternion (R.flat = (q qᵀ).flat @ _QUAT).
_HORN = np.zeros((9, 16))
for (_r, _c), _terms in {
    (0, 0): "+xx +yy +zz", (1, 1): "+xx -yy -zz", (2, 2): "-xx +yy -zz", (3, 3): "-xx -yy +zz",
    (0, 1): "+yz -zy", (0, 2): "+zx -xz", (0, 3): "+xy -yx",
    (1, 2): "+xy +yx", (1, 3): "+zx +xz", (2, 3): "+yz +zy",
}.items():  # fmt: skip
    for _t in _terms.split():
        _HORN[3 * "xyz".index(_t[1]) + "xyz".index(_t[2]), [4 * _r + _c, 4 * _c + _r]] = float(_t[0] + "1")
_QUAT = np.zeros((16, 9))
for (_r, _c), _terms in {
    (0, 0): "+ww +xx -yy -zz", (1, 1): "+ww -xx +yy -zz", (2, 2): "+ww -xx -yy +zz",
    (0, 1): "+xy +yx -wz -zw", (1, 0): "+xy +yx +wz +zw", (0, 2): "+xz +zx +wy +yw", (2, 0): "+xz +zx -wy -yw",
    (1, 2): "+yz +zy -wx -xw", (2, 1): "+yz +zy +wx +xw",
}.items():  # fmt: skip
    for _t in _terms.split():
        _QUAT[4 * "wxyz".index(_t[1]) + "wxyz".index(_t[2]), 3 * _r + _c] += float(_t[0] + "1")
_MINOR = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])
_SIGN = (-1.0) ** np.add.outer(np.arange(4), np.arange(4))
_I4 = np.arange(4)
# A frame is left to the SVD unless N's top eigenvalue stands clear of the next (the adjugate's largest diagonal
# entry, ≤ 64 s₂ for H scaled to unit norm, is above this): there the quaternion is well determined (≤ 1e-12
# from the SVD's rotation on random clusters) and s₂ ≥ 1.5e-4 s₁, so the collinearity test passes.
_GAP_FLOOR = 1e-2
_NEWTON_STEPS = 40
# Newton's last step (|H| = 1): the root is then right to rounding (the next step would be ~1e-24 / the gap).
_NEWTON_TOL = 1e-12


def _horn(H: np.ndarray, bound: np.ndarray, wanted: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotations R (n,3,3) maximising tr(R H), and fast (n,): where R is trusted (elsewhere use the SVD).

    N's largest eigenvalue s₁ + s₂ + sign(det H) s₃ (reflections handled: R is always proper) is the largest
    root of λ⁴ − 2|H|²λ² − 8 det(H) λ + |H|⁴ − 4 e₂(HᵀH), found by Newton from `bound` (above it, where the
    quartic is convex, so the iterates fall to it monotonically); the quaternion is a column of adj(N − λI)."""
    n = len(H)
    norm = np.sqrt((H * H).sum((1, 2)))
    Hn = H / np.where(norm > 0, norm, 1.0)[:, None, None]
    cols = Hn.transpose(0, 2, 1)
    a, b = cols[:, [1, 2, 0]], cols[:, [2, 0, 1]]
    # The cofactors of H, as cross products of its columns: e₂ and det(H) from them suffer no cancellation.
    cof = a[..., [1, 2, 0]] * b[..., [2, 0, 1]] - a[..., [2, 0, 1]] * b[..., [1, 2, 0]]
    # e₂ ≥ s₁²s₂² ≥ s₂²/3, and a frame that passes has s₂ ≥ 1.5e-4: at or below 5e-9 it cannot pass.
    e2 = (cof * cof).sum((1, 2))
    # Frames that cannot pass get the quartic of H = I/√3 (root √3 = the start): Newton waits on none of them.
    cand = wanted & (norm > 0) & (e2 > 5e-9)
    c1 = np.where(cand, -8.0 * (cols[:, 0] * cof[:, 0]).sum(1), -8.0 / np.sqrt(27.0))
    c0 = np.where(cand, 1.0 - 4.0 * e2, -1.0 / 3.0)
    lam = np.where(cand, np.minimum(bound / np.where(norm > 0, norm, 1.0), np.sqrt(3.0)), np.sqrt(3.0))
    for _ in range(_NEWTON_STEPS):
        l2 = lam * lam
        p = (l2 - 2.0) * l2 + c1 * lam + c0
        dp = 4.0 * (l2 - 1.0) * lam + c1
        step = p / np.where(dp > 0, dp, 1.0)
        lam = lam - step
        if np.abs(step).max() < _NEWTON_TOL:
            break
    A = (Hn.reshape(n, 9) @ _HORN).reshape(n, 4, 4)
    A[:, _I4, _I4] -= lam[:, None]
    M = A[:, _MINOR[:, None, :, None], _MINOR[None, :, None, :]]  # (n, 4, 4, 3, 3): the 3x3 minors
    adj = _SIGN * (M[..., 0, 0] * (M[..., 1, 1] * M[..., 2, 2] - M[..., 1, 2] * M[..., 2, 1])
                   - M[..., 0, 1] * (M[..., 1, 0] * M[..., 2, 2] - M[..., 1, 2] * M[..., 2, 0])
                   + M[..., 0, 2] * (M[..., 1, 0] * M[..., 2, 1] - M[..., 1, 1] * M[..., 2, 0]))  # fmt: skip
    # adj = c v vᵀ: the column through its largest diagonal entry is v's best-conditioned multiple.
    diag = np.abs(adj[:, _I4, _I4])
    q = adj[np.arange(n), :, diag.argmax(1)]
    q = q / np.sqrt((q * q).sum(1))[:, None]
    R = ((q[:, :, None] * q[:, None, :]).reshape(n, 16) @ _QUAT).reshape(n, 3, 3)
    fast = cand & (diag.max(1) > _GAP_FLOOR) & (np.abs(step) < _NEWTON_TOL)
    return R, fast


def apply(R: np.ndarray, t: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points (q,3) or (n,q,3) in the body frame → world (n,q,3) for poses R (n,3,3), t (n,3)."""
    return np.asarray(points) @ R.transpose(0, 2, 1) + t[:, None, :]


def to_body(R: np.ndarray, t: np.ndarray, points: np.ndarray) -> np.ndarray:
    """World points (n,q,3) → body frame (n,q,3): Rᵀ (x − t)."""
    return (points - t[:, None, :]) @ R


# Frames the mean shape is averaged over at most (evenly spread); every frame is then aligned to it once.
# A shape from 600 frames differs from the all-frame one by well under a millimetre (its points are means),
# and each alignment of a long take is a batched SVD of every frame.
SHAPE_FRAMES = 600


def procrustes_mean(clouds: np.ndarray, iterations: int = 4, shape_frames: int = SHAPE_FRAMES):
    """Mean shape (q,3) of clouds (n,q,3) with gaps, each frame aligned to it by a rigid transform.

    Generalised Procrustes: start from the frame that sees most points, align every frame, average,
    repeat (on at most `shape_frames` frames spread over the take), then align every frame to the mean.
    Returns (shape, R, t, ok) with shape in the frame of the starting cloud, origin at its point centroid.
    Points never seen stay NaN.
    """
    clouds = np.asarray(clouds, dtype=float)
    seen = np.isfinite(clouds).all(-1)
    start = int(np.argmax(seen.sum(1)))
    shape = clouds[start] - nanmean(clouds[start], axis=0)
    sub = clouds
    if len(clouds) > shape_frames:
        sub = clouds[np.unique(np.append(np.linspace(0, len(clouds) - 1, shape_frames).round().astype(int), start))]
    for _ in range(iterations):
        # Points the current shape lacks borrow the mean of frames that saw them (after alignment).
        R, t, ok = rigid_fit(shape, sub)
        local = to_body(R[ok], t[ok], sub[ok])
        new = nanmean(local, axis=0) if ok.any() else shape
        new = new - nanmean(new, axis=0)
        if np.allclose(np.nan_to_num(new), np.nan_to_num(shape), rtol=0.0, atol=1e-6):  # 1 µm: far below noise
            shape = new
            break
        shape = new
    R, t, ok = rigid_fit(shape, clouds)
    return shape, R, t, ok


def nanmean(x: np.ndarray, axis: int) -> np.ndarray:
    """Mean over `axis` ignoring NaN; NaN (without a warning) where nothing was seen."""
    x = np.asarray(x, dtype=float)
    seen = np.isfinite(x)
    n = seen.sum(axis)
    total = np.where(seen, x, 0.0).sum(axis)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, total / np.maximum(n, 1), np.nan)
