"""Per-body rotations from the fitted optical skeleton, so a marker take can go through the magnetic
solver, the exports and the slippage monitor; and the marker residuals that expose swaps and glitches.

Each frame, each body's fixed points (marker offsets and joint positions from the projection) are fitted
rigidly to the markers and per-frame joint points seen then. A body with one or two markers borrows its
joints' points; with fewer than three non-collinear points the frame is marked invalid for that body.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flockcal.solver.optical.projection import BodyShape, body_points
from flockcal.solver.optical.rigid import apply, rigid_fit


def body_poses(markers: np.ndarray, shapes: list[BodyShape], joint_points: dict[int, np.ndarray], only=None, previous=None):
    """rotations (n,m,3,3) body→world, positions (n,m,3) of each body's origin (its markers'
    centroid), valid (n,m) where the pose is determined. With `only` (bodies) and `previous`
    ((rotations, positions, valid)), the other bodies keep their previous poses."""
    n = markers.shape[0]
    m = len(shapes)
    if only is not None and previous is not None:
        Rs, ts, valid = (x.copy() for x in previous)
    else:
        Rs = np.tile(np.eye(3), (n, m, 1, 1))
        ts = np.zeros((n, m, 3))
        valid = np.zeros((n, m), dtype=bool)
        only = None
    for g, s in enumerate(shapes):
        if only is not None and g not in only:
            continue
        ref = np.concatenate([s.marker_offsets, s.joint_offsets], axis=0)
        obs = body_points(markers, s.markers, joint_points, s.joints)
        R, t, ok = rigid_fit(ref, obs)
        Rs[:, g], ts[:, g], valid[:, g] = R, t, ok
    return Rs, ts, valid


def marker_residuals(markers: np.ndarray, shapes: list[BodyShape], rotations, positions, valid, min_markers: int = 3) -> np.ndarray:
    """(n, k) distance between each seen marker and where its body's pose puts it; NaN if unknown.

    Bodies with fewer than `min_markers` markers are left NaN: their pose leans on joint estimates,
    so a large residual there says little about the marker."""
    n, k, _ = markers.shape
    out = np.full((n, k), np.nan)
    for g, s in enumerate(shapes):
        if len(s.markers) < min_markers:
            continue
        pred = apply(rotations[:, g], positions[:, g], s.marker_offsets)
        d = np.linalg.norm(markers[:, s.markers] - pred, axis=-1)
        out[:, s.markers] = np.where(valid[:, g, None], d, np.nan)
    return out


@dataclass(frozen=True)
class Outliers:
    mask: np.ndarray  # (n, k) marker-frames judged wrong (swapped, ghost, glitch)
    threshold_m: float
    runs: list[tuple[int, int, int, float]]  # (marker, start, stop, worst residual m)
    swaps: list[tuple[int, int, int, int]]  # (start, stop, marker a, marker b) for runs that overlap


PARTNERS = 8  # markers of its body each marker is checked against (the nearest)


def robust_marker_residuals(markers, shapes, joint_points=None, floor_m: float = 0.006, factor: float = 8.0):
    """(n, k) how far each marker is from where its body says, without trusting any pose: the smallest
    change, against the body's fixed shape, of its distances to the other markers of its body.

    A swapped marker changes all of its distances; an honest one keeps at least one (to another honest
    marker), so one bad marker in a body of three or more is pinned on the right marker. Needs two
    other markers of the body in view; NaN otherwise (and for bodies of one or two markers).
    Returns (residuals, threshold) with threshold = max(factor × robust σ, floor)."""
    n, k, _ = markers.shape
    out = np.full((n, k), np.nan)
    for s in shapes:
        q = len(s.markers)
        if q < 3:
            continue
        ref = np.linalg.norm(s.marker_offsets[:, None] - s.marker_offsets[None], axis=-1)
        # Each marker against its PARTNERS nearest markers of the body (a big body that absorbed several
        # segments has tens; the nearest keep their distance best, and a few suffice for "at least one").
        p = min(q - 1, PARTNERS)
        near = np.argsort(np.where(np.isfinite(ref), ref, np.inf) + np.diag(np.full(q, np.inf)), axis=1)[:, :p]  # (q, p)
        m = markers[:, s.markers]
        d = np.linalg.norm(m[:, :, None] - m[:, near], axis=-1)  # (n, q, p), NaN where unseen
        dev = np.abs(d - np.take_along_axis(ref, near, axis=1)[None])
        partners = np.isfinite(dev).sum(2)
        best = np.nanmin(np.where(np.isfinite(dev), dev, np.inf), axis=2)
        out[:, s.markers] = np.where(partners >= 2, best, np.nan)
    fin = out[np.isfinite(out)]
    sigma = 1.4826 * np.median(np.abs(fin - np.median(fin))) if fin.size else 0.0
    return out, max(factor * sigma, floor_m)


def find_outliers(residuals: np.ndarray, factor: float = 8.0, floor_m: float = 0.006, min_run: int = 3) -> Outliers:
    """Marker-frames whose residual exceeds max(factor × robust σ, floor): a swapped label puts a
    marker centimetres from its body, at once (a run that rises and falls smoothly through the threshold,
    by less than half of it in a frame at both ends, both seen, is soft tissue at the end of a range: kept). Two markers off together for
    at least `min_run` frames are reported as a swap; shorter glitches are only masked."""
    r = residuals[np.isfinite(residuals)]
    sigma = 1.4826 * np.median(np.abs(r - np.median(r))) if r.size else 0.0
    thr = max(factor * sigma, floor_m)
    mask = np.nan_to_num(residuals, nan=0.0) > thr
    runs = []
    n = len(residuals)
    for a in np.flatnonzero(mask.any(0)):
        col = np.concatenate([[0], mask[:, a].astype(np.int8), [0]])
        edges = np.flatnonzero(np.diff(col))
        for s, e in zip(edges[::2], edges[1::2]):
            # A swap or glitch starts or ends at once; soft tissue at the end of a range rises and falls
            # smoothly through the threshold: such a run is kept, not masked.
            steps = [residuals[s, a] - residuals[s - 1, a] if s > 0 else np.nan,
                     residuals[e - 1, a] - residuals[e, a] if e < n else np.nan]
            if all(np.isfinite(steps)) and not any(x >= 0.5 * thr for x in steps):
                mask[s:e, a] = False
                continue
            runs.append((int(a), int(s), int(e), float(np.nanmax(np.where(np.isinf(residuals[s:e, a]), np.nan, residuals[s:e, a]), initial=thr))))
    # Pair runs of two different markers that cover nearly the same frames, best overlap first.
    long_runs = [r for r in runs if r[2] - r[1] >= min_run]
    cand = []
    for i, (a, s, e, _) in enumerate(long_runs):
        for j in range(i + 1, len(long_runs)):
            b, s2, e2, _ = long_runs[j]
            if b == a:
                continue
            ratio = (min(e, e2) - max(s, s2)) / min(e - s, e2 - s2)  # a run may be cut short by a gap
            if ratio > 0.5:
                cand.append((ratio, i, j))
    swaps, used = [], set()
    for ratio, i, j in sorted(cand, reverse=True):
        if i in used or j in used:
            continue
        (a, s, e, _), (b, s2, e2, _) = long_runs[i], long_runs[j]
        swaps.append((min(s, s2), max(e, e2), a, b))
        used |= {i, j}
    return Outliers(mask, float(thr), runs, swaps)


def rigid_route_joint(Ri, ti, Rj, tj, ok):
    """The magnetic paper's joint from two bodies' poses: c (in i), l (in j) minimising
    Σ‖R_i c + t_i − R_j l − t_j‖² over frames `ok` (minimum-norm least squares, O'Brien et al. eq. 15)."""
    Q = np.concatenate([Ri[ok], -Rj[ok]], axis=2)  # (f, 3, 6)
    d = tj[ok] - ti[ok]
    A = np.einsum("fki,fkj->ij", Q, Q)
    b = np.einsum("fki,fk->i", Q, d)
    u = np.linalg.pinv(A, rcond=1e-8) @ b
    return u[:3], u[3:]
