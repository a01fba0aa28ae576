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
    U, S, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(U @ Vt))
    d[d == 0] = 1.0
    D = np.ones((len(obs), 3))
    D[:, 2] = d
    R = (Vt.transpose(0, 2, 1) * D[:, None, :]) @ U.transpose(0, 2, 1)  # V diag(1,1,d) Uᵀ
    t = xc - (R @ pc[..., None])[..., 0]
    # Collinear points leave the second singular value at noise level: the rotation about the line is free.
    scale = np.maximum(S[:, 0], 1e-300)
    ok = (count >= min_points) & (S[:, 1] > 1e-6 * scale) & (S[:, 0] > 0)
    return R, t, ok


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
