"""Whether two groups of skin markers articulate — a joint explains their relative motion — judged
against the noise of their own poses (docs/design.md §3a–§3b). Segmentation asks it to decide "two
bodies or one"; the joint fits ask it which part of a merged body is rigid.

A group's pose carries its markers' soft tissue: a marker sliding s metres over the bone turns a Kabsch
fit by about s / lever, so the pose's rotation noise is measured from the group's own residuals. Two
groups turned against each other beyond that noise (the sensor path's margin, ×4 in variance) when a
joint moved between them; skin alone, however large, does not (its turning is in the noise).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flockcal.solver.optical.rigid import apply, procrustes_mean, rigid_fit, to_body

# The sensor path's rule with the sensor path's tolerance scaled to skin markers: a marker cluster's pose
# carries the soft tissue's 5–15 mm, so a centre pinned within 10 mm along every direction (or a hinge whose
# axis moves it at most that) counts as a joint. Real trials sit on either side of it by a margin: the
# joints a trial moved come out at ≤ 9 mm, the ones it did not at ≥ 15 mm (docs/optical.md).
JOINT_TOLERANCE_M = 0.010

# Relative rotation is beyond the poses' noise when its variance about some axis is at least this multiple
# of what the two poses' noise adds there (the sensor path's ROTATION_MARGIN, design.md §3a step 2).
ROTATION_MARGIN = 4.0

# A hinge whose axis runs within this angle of the line between the two groups turns one segment about its
# own length (the forearm's radius about the ulna, skin rolling about a bone): a twist, not a joint between
# two segments, whose axis crosses the limb.
TWIST_DEG = 45.0

FRAMED = 3  # markers a group needs for a pose of its own
MIN_FRAMES = 20  # frames both groups need in common to be judged

# A marker this many times its group's median fit residual off the group's shape (and beyond the outlier
# floor) is a label swap or glitch in that frame, not soft tissue; it is left out of the pose.
OUTLIER_FACTOR = 5.0
OUTLIER_FLOOR_M = 0.015


@dataclass(frozen=True)
class GroupPose:
    """A group's pose in every frame and the rotation noise its own markers give it."""

    R: np.ndarray  # (n, 3, 3) group frame → world
    t: np.ndarray  # (n, 3)
    ok: np.ndarray  # (n,) pose known
    noise: np.ndarray  # (3, 3) rad², covariance of the pose's rotation error, group frame
    sigma_m: float  # skin level: rms of a marker's motion off the group's shape (per coordinate)
    shape: np.ndarray  # (q, 3) the group's mean shape, origin at its centroid
    clean: np.ndarray  # (n, q, 3) the group's markers with swapped or glitching marker-frames blanked


def group_pose(markers: np.ndarray, members, shape: np.ndarray | None = None) -> GroupPose | None:
    """The pose of the markers `members` of (n, k, 3) and its noise; None for fewer than three markers or
    fewer than ten frames with a pose. `shape` (the group's mean shape from other frames) skips the
    generalised Procrustes.

    Noise: each frame's residual after the rigid fit gives σ² = SSE / (3q − 6) (six degrees of freedom
    taken by the fit); a rigid fit of q points p_j with independent errors σ turns by Cov(ω) = σ² J⁻¹,
    J = Σ (‖p_j‖² I − p_j p_jᵀ), so a group nearly on a line is noisy about that line, as it should be."""
    members = np.asarray(members, dtype=int)
    if len(members) < FRAMED:
        return None
    pts = markers[:, members]
    if shape is None:
        shape, R, t, ok = procrustes_mean(pts)
    else:
        R, t, ok = rigid_fit(shape, pts)
    if ok.sum() < 10:
        return None
    res = np.linalg.norm(apply(R, t, shape) - pts, axis=-1)
    fin = res[ok & np.isfinite(res).all(1)] if ok.any() else res[:0]
    limit = max(OUTLIER_FACTOR * float(np.median(fin)) if fin.size else 0.0, OUTLIER_FLOOR_M)
    bad = (res > limit) & np.isfinite(res)
    if bad.any():
        pts = np.where(bad[..., None], np.nan, pts)
        R, t, ok = rigid_fit(shape, pts)
        res = np.linalg.norm(apply(R, t, shape) - pts, axis=-1)
    seen = np.isfinite(res) & ok[:, None]
    dof = 3.0 * seen.sum(1) - 6.0
    use = dof > 0
    sse = (np.where(seen, res, 0.0) ** 2).sum(1)
    sigma2 = float(sse[use].sum() / dof[use].sum()) if use.any() else np.inf
    p = shape - np.nanmean(shape, axis=0)
    p = p[np.isfinite(p).all(1)]
    J = float((p * p).sum()) * np.eye(3) - p.T @ p
    noise = sigma2 * np.linalg.pinv(J, rcond=1e-9, hermitian=True)
    # A direction J cannot turn (all markers on one line) has no rotation measured: infinite noise.
    w, V = np.linalg.eigh(J)
    blind = w <= 1e-9 * max(w.max(), 1e-300)
    if blind.any():
        noise = noise + (V[:, blind] * 1e6) @ V[:, blind].T
    return GroupPose(R, t, ok, noise, float(np.sqrt(sigma2)), shape, pts)


@dataclass(frozen=True)
class Verdict:
    """What joins two groups. `kind`:
    - "skin": their relative rotation is within the poses' noise (whatever the size of the relative motion);
    - "twist": a hinge about an axis along the line between them (one segment turning about its length);
    - "joint": turned beyond the noise, and a joint pins the centre (a ball, or a hinge across the limb);
    - "moved": turned beyond the noise, but no joint pins the centre;
    - "unjudged": a group has no pose (under three markers) or they share too few frames."""

    kind: str
    rotation_ratio: float  # largest relative-rotation variance over the noise's, along one axis (NaN: unjudged)
    joint_error_m: float  # the centre's error along its least-pinned direction, hinge axis aside (inf: not pinned)
    hinge: bool = False
    across_m: float = float("nan")  # the error across the least-turned direction (what a hinge would need)

    def to_dict(self) -> dict:
        def num(x):
            return float(x) if np.isfinite(x) else None

        return {"kind": self.kind, "rotation_ratio": num(self.rotation_ratio), "joint_error_m": num(self.joint_error_m),
                "hinge": bool(self.hinge)}


UNJUDGED = Verdict("unjudged", float("nan"), float("nan"))


def relative_motion(a: np.ndarray, b: np.ndarray, low: float = 0.05, high: float = 0.95) -> float:
    """Mean over the marker pairs of a (n, qa, 3) and b (n, qb, 3) of the `low`–`high` quantile range of
    their distance (m): the size of their relative motion also when it happened in only a part of the take
    (one limb after another), which a 10–90 % range does not see. Swapped or glitching marker-frames are
    best blanked first (a group's `clean` markers); a swap in under 5 % of the frames does not count."""
    from flockcal.solver.optical.segmentation import quantile_range

    d = np.linalg.norm(a[:, :, None, :] - b[:, None, :, :], axis=-1)
    r = quantile_range(d, low=low, high=high)
    r = r[np.isfinite(r)]
    return float(r.mean()) if r.size else float("inf")


def relative_rotation(A: GroupPose, B: GroupPose, ok: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(mean rotation of B in A's frame (3, 3), rotation vectors ω (f, 3) of each frame about it, A's frame)."""
    Q = A.R[ok].transpose(0, 2, 1) @ B.R[ok]
    U, _, Vt = np.linalg.svd(Q.mean(0))
    Qm = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
    E = Q @ Qm.T
    # The skew part gives sin θ · axis: exact to first order, monotonic up to 90°, which is all a variance
    # compared with millimetre-level noise needs.
    w = 0.5 * np.stack([E[:, 2, 1] - E[:, 1, 2], E[:, 0, 2] - E[:, 2, 0], E[:, 1, 0] - E[:, 0, 1]], axis=1)
    return Qm, w


def rotation_ratio(A: GroupPose, B: GroupPose, ok: np.ndarray) -> float:
    """Largest generalised eigenvalue of the relative rotation's covariance over the two poses' noise."""
    Qm, w = relative_rotation(A, B, ok)
    C = np.cov(w.T)
    N = A.noise + Qm @ B.noise @ Qm.T
    L = np.linalg.cholesky(N + 1e-18 * np.eye(3))
    Li = np.linalg.inv(L)
    return float(np.linalg.eigvalsh(Li @ C @ Li.T).max())


def direction_ratios(A: GroupPose, pairs: np.ndarray) -> np.ndarray:
    """For groups of two markers `pairs` (n, S, 2, 3), each with a direction but no pose: the largest
    variance of its direction in A's frame, across the direction, over what A's pose noise and the pair's
    own skin add there (the pair's skin read from how much its own distance varies); (S,), NaN where the
    pair and A share too few frames."""
    y = to_body(np.where(A.ok[:, None, None], A.R, np.eye(3)), A.t, pairs.reshape(len(pairs), -1, 3))
    y = y.reshape(pairs.shape)  # (n, S, 2, 3) in A's frame
    ok = A.ok[:, None] & np.isfinite(y).all(axis=(2, 3))  # (n, S)
    cnt = ok.sum(0)
    v = y[:, :, 1] - y[:, :, 0]
    d = np.linalg.norm(v, axis=-1)
    u = np.where(ok[..., None], v / np.where(ok, d, 1.0)[..., None], 0.0)
    um = u.sum(0) / np.maximum(cnt, 1)[:, None]
    um /= np.maximum(np.linalg.norm(um, axis=1), 1e-300)[:, None]
    du = np.where(ok[..., None], u - u.sum(0)[None] / np.maximum(cnt, 1)[None, :, None], 0.0)
    C = np.einsum("nsi,nsj->sij", du, du) / np.maximum(cnt - 1, 1)[:, None, None]
    P = np.eye(3)[None] - np.einsum("si,sj->sij", um, um)
    C = P @ C @ P
    dm = np.where(ok, d, 0.0).sum(0) / np.maximum(cnt, 1)
    skin = np.where(ok, (d - dm[None]) ** 2, 0.0).sum(0) / np.maximum(cnt, 1) / 2.0  # σ² per coordinate
    zero = np.zeros(len(um))
    ux = np.stack([np.stack([zero, -um[:, 2], um[:, 1]], -1), np.stack([um[:, 2], zero, -um[:, 0]], -1),
                   np.stack([-um[:, 1], um[:, 0], zero], -1)], axis=1)
    N = ux @ A.noise @ ux.transpose(0, 2, 1) + (2.0 * skin / np.maximum(dm, 1e-12) ** 2)[:, None, None] * P
    # Across the direction only (the plane P): whiten there and read the largest ratio.
    w, V = np.linalg.eigh(N)
    plane = np.take_along_axis(V, np.argsort(w, axis=1)[:, None, 1:], axis=2)  # N's null direction is along the pair
    Np, Cp = plane.transpose(0, 2, 1) @ N @ plane, plane.transpose(0, 2, 1) @ C @ plane
    Li = np.linalg.inv(np.linalg.cholesky(Np + 1e-18 * np.eye(2)[None]))
    lam = np.linalg.eigvalsh(Li @ Cp @ Li.transpose(0, 2, 1)).max(axis=1)
    return np.where(cnt >= MIN_FRAMES, lam, np.nan)


SCORE_BLOCK = 64  # frames per batch-means block, as the accumulator's (design.md §3a)


@dataclass(frozen=True)
class PointJoints:
    """Joints between a framed group A and groups of two markers with no pose of their own (S of them)."""

    verdicts: list  # (S,) Verdict
    centre: np.ndarray  # (S, 3) the joint in A's frame
    rms_m: np.ndarray  # (S,) rms of the two markers' distance from the centre about their constant radii
    axis: np.ndarray  # (S, 3) the least-pinned direction in A's frame (a hinge's axis)


def point_joints(A: GroupPose, pts: np.ndarray, tolerance: float = JOINT_TOLERANCE_M) -> PointJoints:
    """The joints between a framed group A and S pairs of markers `pts` (n, S, 2, 3), each with no pose
    of its own: for each, a point fixed in A's frame that keeps a constant distance to both markers (Kirk's
    joint, seen from A; with two markers a body's pose is free only about the line between them, which
    the distances to a point do not see). Linear in A's frame: ‖y‖² − mean = 2 (y − ȳ)ᵀ c per marker.
    Pinned along a direction when its standard error — the larger of the classical and the batch-means one
    (blocks of SCORE_BLOCK frames, read at the sensor path's upper confidence bound) — is within
    `tolerance`; a ball has all three pinned, a hinge all but the least-spread one. The turn itself is
    judged first: a pair's direction beyond its noise (`direction_ratios`), else "skin".

    One constant point per take is what a pose-to-pose pair fit asks of two posed bodies: a pair with no
    joint between them leaves centimetres of residual (`rms_m`), where Kirk's point, free in every frame,
    fits almost any two groups to a few millimetres."""
    from flockcal.solver.fits import _upper_chi2_factor

    n, S, q, _ = pts.shape
    lam = direction_ratios(A, pts[:, :, :2])
    frames = np.flatnonzero(A.ok)
    y = to_body(A.R[frames], A.t[frames], pts[frames].reshape(len(frames), -1, 3)).reshape(len(frames), S, q, 3)
    seen = np.isfinite(y).all(-1)  # (f, S, q)
    cnt = np.maximum(seen.sum(0), 1)
    y0 = np.where(seen[..., None], y, 0.0)
    ybar = y0.sum(0) / cnt[..., None]  # (S, q, 3)
    X = 2.0 * np.where(seen[..., None], y - ybar[None], 0.0)
    ybar[~seen.any(0)] = np.nan  # a marker never seen (padding) is nowhere
    z = (y0**2).sum(-1)
    z = np.where(seen, z - z.sum(0)[None] / cnt[None], 0.0)
    H = np.einsum("fsqi,fsqj->sij", X, X) + 1e-30 * np.eye(3)[None]
    c = np.linalg.solve(H, np.einsum("fsqi,fsq->si", X, z)[..., None])[..., 0]  # (S, 3)
    e = np.where(seen, z - np.einsum("fsqi,si->fsq", X, c), 0.0)  # (f, S, q), m²
    dist = np.linalg.norm(y - c[None, :, None], axis=-1)
    dist0 = np.where(seen, dist, 0.0)
    radius = dist0.sum(0) / cnt
    rms = np.sqrt(np.where(seen, (dist - radius[None]) ** 2, 0.0).sum((0, 2)) / np.maximum(seen.sum((0, 2)), 1))
    m = seen.sum((0, 2))
    w, V = np.linalg.eigh(H)
    w = np.maximum(w, 1e-30)
    var_cl = ((e**2).sum((0, 2)) / np.maximum(m - 3 - q, 1))[:, None] / w
    g = np.einsum("fsqi,fsq->fsi", X, e)
    nb = len(frames) // SCORE_BLOCK
    if nb >= 2:
        gb = g[: nb * SCORE_BLOCK].reshape(nb, SCORE_BLOCK, S, 3).sum(1)  # (nb, S, 3)
        G = np.einsum("bsi,bsj->sij", gb, gb)
        Sd = np.einsum("sik,sij,sjk->sk", V, G, V)
        var_bm = Sd / w**2 * _upper_chi2_factor(np.array([max(nb - 1, 1)], dtype=float))[0]
    else:
        var_bm = np.full((S, 3), np.inf)
    err = np.sqrt(np.maximum(var_cl, var_bm))  # ascending spread: err[:, 0] is the least-pinned direction
    # A hinge leaves its point along the axis to a rule (Kirk's penalty: the point nearest the markers):
    # the axis's point nearest the middle of A's centroid and the pair's, before it is judged to lie between
    # them (least squares along a direction barely turned can put it anywhere on the axis).
    free = V[:, :, 0]
    hinge = ~(err <= tolerance).all(1) & (err[:, 1:] <= tolerance).all(1)
    slide = np.einsum("si,si->s", free, 0.5 * np.nanmean(ybar, axis=1) - c)
    c = np.where(hinge[:, None], c + slide[:, None] * free, c)
    verdicts = [point_verdict(A, lam[s], err[s], c[s], ybar[s], free[s], tolerance) for s in range(S)]
    return PointJoints(verdicts, c, np.where(np.isfinite(lam), rms, np.nan), free)


def point_verdict(A: GroupPose, lam: float, err: np.ndarray, c: np.ndarray, ybar: np.ndarray, free: np.ndarray,
                  tolerance: float) -> Verdict:
    """The verdict on one point joint (`point_joints`): skin, moved (not pinned, or not between the two
    groups, or a hinge about the line between them) or joint."""
    if not np.isfinite(lam):
        return UNJUDGED
    if lam < ROTATION_MARGIN:
        return Verdict("skin", lam, float("nan"))
    ball = bool((err <= tolerance).all())
    hinge = not ball and bool((err[1:] <= tolerance).all())
    worst = float(err.max() if ball else err[1:].max())
    if not (ball or hinge):
        return Verdict("moved", lam, worst)
    line = np.nanmean(ybar, axis=0)  # the pair's midpoint from A's origin (A's centroid)
    reach_a = float(np.nanmin(np.linalg.norm(A.shape - c, axis=1)))
    reach_b = float(np.nanmin(np.linalg.norm(ybar - c, axis=1)))
    if max(reach_a, reach_b) > float(np.linalg.norm(line)):
        return Verdict("moved", lam, worst, hinge=hinge)
    if hinge and abs(float(free @ line)) >= np.cos(np.radians(TWIST_DEG)) * float(np.linalg.norm(line)):
        # A turn about the line between them: with two markers a twist cannot be told from a joint whose
        # other turns the pair does not show; the size decides.
        return Verdict("moved", lam, worst, hinge=True)
    return Verdict("joint", lam, worst, hinge=hinge)


def point_joint(A: GroupPose, pts: np.ndarray, tolerance: float = JOINT_TOLERANCE_M) -> Verdict:
    """The verdict on a framed group A and one or two markers `pts` (n, q, 3) with no pose of their own
    (`point_joints`); a lone marker has no direction, and stays unjudged."""
    if pts.shape[1] < 2:
        return UNJUDGED
    return point_joints(A, pts[:, None, :2], tolerance).verdicts[0]


def second_ratio(A: GroupPose, B: GroupPose, ok: np.ndarray) -> float:
    """The second largest generalised eigenvalue: rotation beyond noise about a second axis too."""
    Qm, w = relative_rotation(A, B, ok)
    C = np.cov(w.T)
    N = A.noise + Qm @ B.noise @ Qm.T
    Li = np.linalg.inv(np.linalg.cholesky(N + 1e-18 * np.eye(3)))
    return float(np.linalg.eigvalsh(Li @ C @ Li.T)[1])


def judge(A: GroupPose | None, B: GroupPose | None, tolerance: float = JOINT_TOLERANCE_M) -> Verdict:
    """The verdict on groups A and B (see `Verdict`): the rotation test first, then the sensor path's pair
    fit (`flockcal.solver.fits.pair_fits`, batch-means errors) on the two poses."""
    from flockcal.solver.accumulator import GramAccumulator
    from flockcal.solver.fits import pair_fits

    if A is None or B is None:
        return UNJUDGED
    ok = A.ok & B.ok
    if ok.sum() < MIN_FRAMES:
        return UNJUDGED
    lam = rotation_ratio(A, B, ok)
    if not lam >= ROTATION_MARGIN:
        return Verdict("skin", lam, float("nan"))
    acc = GramAccumulator(2)
    eye = np.eye(3)
    R = np.stack([np.where(A.ok[:, None, None], A.R, eye), np.where(B.ok[:, None, None], B.R, eye)], axis=1)
    t = np.stack([np.where(A.ok[:, None], A.t, 0.0), np.where(B.ok[:, None], B.t, 0.0)], axis=1)
    acc.add_poses(R, t, np.stack([A.ok, B.ok], axis=1))
    pf = pair_fits(acc, np.array([[0, 1]]), tolerance=tolerance)
    err = pf.direction_error[0]
    worst = float(err[1:].max() if pf.hinge[0] else err.max())
    if not pf.determined[0]:
        return Verdict("moved", lam, worst, across_m=float(err[1:].max()))
    # Where the joint is, in A's frame, and the line between the groups (B's origin, its markers' centroid).
    line = np.nanmedian(((B.t[ok] - A.t[ok])[:, None, :] @ A.R[ok])[:, 0], axis=0)
    if not between(A.shape, B.shape, pf.c[0], pf.l[0], float(np.linalg.norm(line))):
        return Verdict("moved", lam, worst, hinge=bool(pf.hinge[0]))
    if pf.hinge[0]:
        cos = abs(float(pf.axis_i[0] @ line)) / max(float(np.linalg.norm(line)), 1e-12)
        if cos >= np.cos(np.radians(TWIST_DEG)) and second_ratio(A, B, ok) < ROTATION_MARGIN:
            return Verdict("twist", lam, worst, hinge=True)
    return Verdict("joint", lam, worst, hinge=bool(pf.hinge[0]))


def between(shape_a: np.ndarray, shape_b: np.ndarray, c: np.ndarray, l: np.ndarray, apart: float) -> bool:
    """A joint between two segments lies between them: its centre (a hinge: its point on the axis) no
    farther from the nearest marker of either group than the groups' centroids are apart. A 'joint' farther out is the pivot
    of skin sliding in step with the motion (a slide linear in an angle looks, to a rigid fit, like a turn
    about a distant point: design.md §3b)."""
    def reach(shape, point):
        return float(np.nanmin(np.linalg.norm(shape - point, axis=1)))

    return reach(shape_a, c) <= apart and reach(shape_b, l) <= apart
