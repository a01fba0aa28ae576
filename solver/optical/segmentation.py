"""Which markers ride on one rigid body, on real skin markers: groups that moved relative to each other
beyond what soft tissue does are split; groups that never did stay one body, however many segments.

Two stages, both judged against one physical tolerance (the relative motion soft tissue alone can make):
average-linkage clustering of every pair's distance range, then a merge and reassignment step that looks
at each marker from the other bodies' own frames, which sees small rotations a distance cannot.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flockcal.errors import FlockcalError
from flockcal.solver.optical.rigid import procrustes_mean, rigid_fit, to_body

# Skin markers slide over the bone by 5–15 mm at the ends of a joint's range (soft-tissue artefact), so two
# markers of one segment can change their distance by up to about this much; relative motion within it is
# read as "did not move relative to each other". A range is the 10th–90th percentile spread over the take
# (a label swap or glitch in under a tenth of the frames does not widen it).
RIGID_TOLERANCE_M = 0.015
LOW_Q, HIGH_Q = 0.10, 0.90

# Frames used for the ranges: relative motion is slow next to 100 Hz, and more frames change a range by
# well under a millimetre while the cost grows with frames × markers².
SEGMENT_FRAMES = 250

# A body needs this many markers to have a frame of its own (three non-collinear points).
FRAMED = 3
LEAVE_OUT_BELOW = 8  # bodies this small judge their own markers with each left out of the fit


# Stands in for "no frame to see it from" inside sums (any real motion is far below a kilometre).
UNSEEN_M = 1e3


class SegmentationError(FlockcalError):
    """The markers could not be grouped into rigid bodies."""


@dataclass(frozen=True)
class Segmentation:
    labels: np.ndarray  # (k,) body index of every marker, bodies numbered by their first marker
    n_groups: int
    tolerance_m: float  # the relative motion read as "rigid"
    distance_range: np.ndarray  # (k, k) 10–90 % range of every inter-marker distance (m); inf: never seen together
    internal_motion: np.ndarray  # (G,) mean distance range inside each body (m); 0 for a single marker
    frames: np.ndarray  # frames the ranges were read on

    @property
    def groups(self) -> list[np.ndarray]:
        return [np.flatnonzero(self.labels == g) for g in range(self.n_groups)]


def quantile_range(x: np.ndarray, axis: int = 0, low: float = LOW_Q, high: float = HIGH_Q, min_count: int = 5) -> np.ndarray:
    """high − low quantile of `x` along `axis`, NaN ignored; inf where fewer than `min_count` values.

    One sort for both quantiles (nanquantile sorts per call and is ~10× slower on (frames, k, k))."""
    s = np.sort(np.moveaxis(np.asarray(x, dtype=float), axis, 0), axis=0)  # NaN sort last
    cnt = np.isfinite(s).sum(0)
    last = np.maximum(cnt - 1, 0)
    lo = np.take_along_axis(s, np.round(low * last).astype(int)[None], 0)[0]
    hi = np.take_along_axis(s, np.round(high * last).astype(int)[None], 0)[0]
    return np.where(cnt >= min_count, hi - lo, np.inf)


def distance_ranges(markers: np.ndarray) -> np.ndarray:
    """(k, k) 10–90 % range of every inter-marker distance over the frames given; inf where two markers
    were seen together in too few frames to say; 0 on the diagonal."""
    d = np.linalg.norm(markers[:, :, None, :] - markers[:, None, :, :], axis=-1)
    out = quantile_range(d)
    np.fill_diagonal(out, 0.0)
    return out


def linkage_labels(ranges: np.ndarray, tolerance: float, n_groups: int | None = None) -> np.ndarray:
    """Average-linkage (UPGMA) clusters of the distance ranges, merged while the closest two clusters'
    mean range is within `tolerance` (or until `n_groups` remain).

    Average linkage, not single: markers near a joint keep their distance to the other segment's markers
    nearly constant, so one such pair must not join two segments; the mean over all pairs does not care.
    Written out (k − 1 merges of a k × k matrix) rather than taken from scipy.cluster, whose import alone
    costs a third of the time budget of a small take."""
    k = len(ranges)
    finite = np.isfinite(ranges)
    big = 10.0 * max(float(ranges[finite].max()) if finite.any() else 1.0, tolerance)
    D = np.where(finite, ranges, big).astype(float)
    np.fill_diagonal(D, np.inf)
    size = np.ones(k)
    labels = np.arange(k)
    target = 1 if n_groups is None else max(1, min(int(n_groups), k))
    for _ in range(k - target):
        a, b = np.unravel_index(np.argmin(D), D.shape)
        if n_groups is None and not D[a, b] <= tolerance:
            break
        # The merged cluster's mean range to every other: the size-weighted mean of its two parts'.
        row = (size[a] * D[a] + size[b] * D[b]) / (size[a] + size[b])
        D[a], D[:, a] = row, row
        D[a, a] = np.inf
        D[b], D[:, b] = np.inf, np.inf
        size[a] += size[b]
        labels[labels == b] = a
    return canonical(labels)


def canonical(labels: np.ndarray) -> np.ndarray:
    """Renumber groups 0..G−1 in order of their first marker (equal partitions compare equal)."""
    _, first, inverse = np.unique(labels, return_index=True, return_inverse=True)
    rank = np.empty(len(first), dtype=int)
    rank[np.argsort(first)] = np.arange(len(first))
    return rank[inverse.reshape(-1)]


def motion_in_frames(markers: np.ndarray, labels: np.ndarray, cache: dict | None = None) -> np.ndarray:
    """(k, G) how far each marker moves in each body's own frame (2 × the 90 % quantile of its distance
    from its median position there: comparable to a distance range); inf for bodies without a frame.
    `cache` keeps each body's column by its members, so a merge recomputes only the merged body."""
    k = markers.shape[1]
    G = int(labels.max()) + 1
    out = np.full((k, G), np.inf)
    cache = {} if cache is None else cache
    for g in range(G):
        members = np.flatnonzero(labels == g)
        key = tuple(members.tolist())
        if key not in cache:
            cache[key] = body_motion(markers, members)
        out[:, g] = cache[key]
    return out


def body_motion(markers: np.ndarray, members: np.ndarray) -> np.ndarray:
    """(k,) every marker's motion in the frame of the body made of `members` (inf: no frame).

    A member is left out of the fit that judges it while the body keeps three markers and is small
    enough for one marker to hold it still (a marker pulls a fit of q markers by about 1/q of its motion;
    at LEAVE_OUT_BELOW markers and more that is within the tolerance's rounding and not worth a refit)."""
    out = np.full(markers.shape[1], np.inf)
    if len(members) < FRAMED:
        return out
    shape, R, t, ok = procrustes_mean(markers[:, members])
    if ok.sum() < 10:
        return out
    out[:] = spread_in_frame(markers[ok], R[ok], t[ok])
    if FRAMED < len(members) < LEAVE_OUT_BELOW:
        for pos, i in enumerate(members):
            rest = np.delete(np.arange(len(members)), pos)
            Ri, ti, oki = rigid_fit(shape[rest], markers[:, members[rest]])
            if oki.sum() >= 10:
                out[i] = spread_in_frame(markers[oki][:, [i]], Ri[oki], ti[oki])[0]
    return out


def spread_in_frame(markers: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(q,) 2 × 90 % quantile of each marker's distance from its median position in the frame (R, t)."""
    y = to_body(R, t, markers)  # (f, q, 3)
    med = np.nanmedian(y, axis=0)
    dev = np.linalg.norm(y - med[None], axis=-1)
    s = np.sort(dev, axis=0)
    cnt = np.isfinite(s).sum(0)
    q = np.take_along_axis(s, np.round(HIGH_Q * np.maximum(cnt - 1, 0)).astype(int)[None], 0)[0]
    return np.where(cnt >= 5, 2.0 * q, np.inf)


def merge_still_bodies(markers: np.ndarray, labels: np.ndarray, tolerance: float, n_groups: int | None = None) -> np.ndarray:
    """Merge bodies that did not move relative to each other and move markers to the body they are still
    in, judged in the bodies' own frames (a rotation of a few degrees moves a marker a long way from the
    joint while hardly changing distances to markers near it)."""
    labels = canonical(labels)
    cache: dict = {}
    for _ in range(len(labels)):
        G = int(labels.max()) + 1
        if G == 1 or (n_groups is not None and G <= n_groups):
            break
        motion = motion_in_frames(markers, labels, cache)
        # Body B as seen from A: mean motion of B's markers in A's frame; the better-framed view decides.
        member = np.eye(G, dtype=bool)[labels]  # (k, G)
        capped = np.minimum(motion, UNSEEN_M)  # inf · 0 would be NaN in the product
        seen_from = (capped.T @ member) / np.maximum(member.sum(0), 1)[None]  # (A, B)
        seen_from[seen_from >= UNSEEN_M] = np.inf
        pair = np.minimum(seen_from, seen_from.T)
        np.fill_diagonal(pair, np.inf)
        a, b = np.unravel_index(np.argmin(pair), pair.shape)
        limit = np.inf if n_groups is not None else tolerance
        if not pair[a, b] <= limit:
            labels = reassign(motion, labels, tolerance)
            break
        labels = canonical(np.where(labels == b, a, labels))
    return labels


def reassign(motion: np.ndarray, labels: np.ndarray, tolerance: float) -> np.ndarray:
    """Each marker to the framed body it moves least in, when it is still there (within `tolerance`) and
    stiller than in its own body; a body is never emptied below a frame by this."""
    labels = labels.copy()
    best = np.argmin(motion, axis=1)
    gain = motion[np.arange(len(labels)), best]
    own = motion[np.arange(len(labels)), labels]
    for i in np.argsort(gain):
        g = best[i]
        if g == labels[i] or not gain[i] <= tolerance or not gain[i] < own[i]:
            continue
        size = np.sum(labels == labels[i])
        if size == FRAMED:  # leaving would cost the body its frame
            continue
        labels[i] = g
    return canonical(labels)


def segment_markers(
    markers: np.ndarray,
    tolerance: float = RIGID_TOLERANCE_M,
    n_groups: int | None = None,
    max_frames: int = SEGMENT_FRAMES,
) -> Segmentation:
    """Group the k markers of a take (n, k, 3, NaN gaps) into rigid bodies that moved relative to each
    other by more than `tolerance` (metres of 10–90 % relative motion); `n_groups` forces the count."""
    markers = np.asarray(markers, dtype=float)
    if markers.ndim != 3 or markers.shape[2] != 3:
        raise SegmentationError(f"markers must have shape (frames, markers, 3), got {markers.shape}")
    n, k, _ = markers.shape
    if k < 2:
        raise SegmentationError(f"need at least two markers to find rigid bodies, got {k}")
    if not tolerance > 0:
        raise SegmentationError(f"the rigid tolerance must be positive, got {tolerance!r} m")
    frames = np.unique(np.linspace(0, n - 1, min(n, max_frames)).round().astype(int))
    M = markers[frames]
    ranges = distance_ranges(M)
    labels = linkage_labels(ranges, tolerance, n_groups)
    labels = merge_still_bodies(M, labels, tolerance, n_groups)
    G = int(labels.max()) + 1
    internal = np.zeros(G)
    for g in range(G):
        idx = np.flatnonzero(labels == g)
        if len(idx) > 1:
            block = ranges[np.ix_(idx, idx)][~np.eye(len(idx), dtype=bool)]
            block = block[np.isfinite(block)]
            internal[g] = float(block.mean()) if block.size else np.nan
    return Segmentation(labels, G, float(tolerance), ranges, internal, frames)
