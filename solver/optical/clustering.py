"""Which markers ride on the same rigid body: spectral clustering of inter-marker distance spread.

Kirk et al. 2005 §2: markers on one bone keep their mutual distances, so the standard deviation of each
pair's distance over time is near the noise level inside a body and large across a joint. Several
jittered frame samplings are clustered; the clustering with the smallest within-group spread wins
(RANSAC-style). Spreads are taken robustly inside time windows and the largest kept, so a marker
swap in part of the take does not split a body while a joint exercised only once still separates two.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.cluster.vq import kmeans2

from flockcal.errors import FlockcalError


class ClusteringError(FlockcalError):
    """The markers could not be grouped into rigid bodies."""


@dataclass(frozen=True)
class Clustering:
    labels: np.ndarray  # (k,) group index of every marker; groups numbered by their first marker
    n_groups: int
    distance_std: np.ndarray  # (k, k) std of inter-marker distance (m) in the chosen sampling; inf: never seen together
    within_std: float  # mean within-group std of the chosen sampling (m)
    eigenvalues: np.ndarray  # normalised-Laplacian spectrum of the chosen sampling
    votes: np.ndarray  # (samplings,) number of groups each sampling chose

    @property
    def groups(self) -> list[np.ndarray]:
        return [np.flatnonzero(self.labels == g) for g in range(self.n_groups)]


def jittered_frames(n: int, count: int, window: float, rng: np.random.Generator) -> np.ndarray:
    """`count` sorted frame indices spread uniformly (one per stratum, jittered) over a random window."""
    span = max(1, min(n, int(round(window * n))))
    start = int(rng.integers(0, n - span + 1))
    count = min(count, span)
    pos = (np.arange(count) + rng.random(count)) * (span / count)
    return np.unique(start + np.minimum(pos.astype(int), span - 1))


def distance_std(markers: np.ndarray, frames: np.ndarray | None = None, min_frames: int = 5, robust: bool = False) -> np.ndarray:
    """(k, k) standard deviation over `frames` of every inter-marker distance; inf where two markers
    were seen together in fewer than `min_frames` frames (nothing says they are rigidly attached).

    robust: 1.4826 × median absolute deviation instead, which a label swap in a few percent of the
    frames cannot inflate (a plain std is √(fraction) × the jump: 2 % of frames off by 10 cm give 1.4 cm).
    """
    m = markers if frames is None else markers[frames]
    d = np.linalg.norm(m[:, :, None, :] - m[:, None, :, :], axis=-1)  # (s, k, k), NaN where unseen
    seen = np.isfinite(d)
    cnt = seen.sum(0)
    dz = np.where(seen, d, 0.0)
    mean = dz.sum(0) / np.maximum(cnt, 1)
    if robust:
        med = np.nanmedian(np.where(seen, d, np.nan), axis=0) if seen.any() else mean
        out = 1.4826 * np.nanmedian(np.where(seen, np.abs(d - med), np.nan), axis=0)
        out = np.where(np.isfinite(out), out, np.inf)
    else:
        var = (np.where(seen, d - mean, 0.0) ** 2).sum(0) / np.maximum(cnt - 1, 1)
        out = np.sqrt(var)
    out[cnt < min_frames] = np.inf
    np.fill_diagonal(out, 0.0)
    return out


def affinity(std: np.ndarray, floor: float = 1e-4) -> np.ndarray:
    """Self-tuning affinity exp(−s²/(σ_i σ_j)), σ_i = marker i's smallest spread to any other marker.

    The local scale adapts to the noise level without a tuning constant; `floor` (m) keeps exact data
    from dividing by zero. A lone marker's σ is a cross-joint spread, so it stays its own group.
    """
    k = len(std)
    s = np.where(np.isfinite(std), std, np.inf)
    off = s + np.diag(np.full(k, np.inf))
    sigma = np.maximum(off.min(1), floor)
    sigma = np.where(np.isfinite(sigma), sigma, 1.0)
    with np.errstate(over="ignore"):
        W = np.exp(-(s**2) / np.outer(sigma, sigma))
    np.fill_diagonal(W, 0.0)
    return W


def spectral_labels(W: np.ndarray, n_groups: int | None = None, seed: int = 0):
    """Labels (k,) by normalised spectral clustering (Ng, Jordan, Weiss); returns (labels, G, eigenvalues).

    The number of groups G, unless given, is the largest eigengap of the normalised Laplacian among the
    eigenvalues below 0.5 (well-separated rigid bodies give G near-zero eigenvalues; the rest sit near 1–2).
    """
    k = len(W)
    deg = W.sum(1)
    inv = np.where(deg > 1e-12, 1.0 / np.sqrt(np.maximum(deg, 1e-300)), 0.0)
    L = np.eye(k) - inv[:, None] * W * inv[None, :]
    L[deg <= 1e-12, deg <= 1e-12] = 0.0  # an isolated marker is a component of its own
    vals, vecs = np.linalg.eigh(L)
    if n_groups is None:
        if k == 1:
            n_groups = 1
        else:
            gaps = np.diff(vals)
            allowed = vals[:-1] < 0.5
            n_groups = int(np.argmax(np.where(allowed, gaps, -np.inf))) + 1 if allowed.any() else k
    G = int(min(max(n_groups, 1), k))
    emb = vecs[:, :G].copy()
    emb /= np.maximum(np.linalg.norm(emb, axis=1, keepdims=True), 1e-12)
    # Farthest-first seeds: the rows of separate bodies are near-orthogonal, so this lands one per body.
    seeds = [0]
    for _ in range(G - 1):
        dist = np.min(np.linalg.norm(emb[:, None, :] - emb[seeds][None], axis=-1), axis=1)
        seeds.append(int(np.argmax(dist)))
    _, labels = kmeans2(emb, emb[seeds], minit="matrix", seed=seed)
    return canonical(labels), G, vals


def canonical(labels: np.ndarray) -> np.ndarray:
    """Renumber groups 0..G−1 in order of their first marker (so equal clusterings compare equal)."""
    _, first = np.unique(labels, return_index=True)
    order = np.argsort(first)
    remap = np.empty(labels.max() + 1, dtype=int)
    remap[np.unique(labels)[order]] = np.arange(len(order))
    return remap[labels]


def within_spread(std: np.ndarray, labels: np.ndarray) -> float:
    """Mean distance std over pairs in the same group (0 when every group is a single marker)."""
    same = labels[:, None] == labels[None, :]
    np.fill_diagonal(same, False)
    if not same.any():
        return 0.0
    vals = std[same]
    return float(np.mean(np.where(np.isfinite(vals), vals, 1.0)))


def windowed_spread(markers: np.ndarray, windows: list[np.ndarray]) -> np.ndarray:
    """(k, k) largest, over the windows, of the robust spread (MAD) of each distance inside a window.

    A joint that moves for over half of some window shows; a swap or glitch shorter than half of every
    window it touches does not. A joint exercised in one part of the take only (one joint at a time,
    as in a calibration routine) is still seen, which a whole-take robust spread would miss."""
    out = None
    for frames in windows:
        s = distance_std(markers, frames, robust=True)
        s = np.where(np.isfinite(s), s, -np.inf)
        out = s if out is None else np.maximum(out, s)
    out = np.where(np.isfinite(out) & (out >= 0), out, np.inf)
    np.fill_diagonal(out, 0.0)
    return out


def cluster_markers(
    markers: np.ndarray,
    n_groups: int | None = None,
    samplings: int = 8,
    frames_per_window: int = 40,
    window_frames: int | None = None,
    seed: int = 0,
) -> Clustering:
    """Group the k markers of a take (n, k, 3) into rigid bodies.

    Each sampling cuts the take into windows of `window_frames` (default n/6, at least 60) at a random
    offset and draws `frames_per_window` jittered-uniform frames in each; the affinity uses
    `windowed_spread`. The number of groups is the most common eigengap choice over samplings (or
    `n_groups`); among the samplings that chose it, the one with the smallest mean within-group plain
    std over its frames is kept (RANSAC-style: a sampling that caught a swap scores worse).
    """
    markers = np.asarray(markers, dtype=float)
    if markers.ndim != 3 or markers.shape[2] != 3:
        raise ClusteringError(f"markers must have shape (frames, markers, 3), got {markers.shape}")
    n, k, _ = markers.shape
    if k < 2:
        raise ClusteringError(f"need at least two markers to find rigid bodies, got {k}")
    rng = np.random.default_rng(seed)
    wlen = max(60, n // 6) if window_frames is None else int(window_frames)
    wlen = min(wlen, n)
    results = []
    for s in range(samplings):
        offset = int(rng.integers(0, wlen)) if n > wlen else 0
        starts = np.arange(offset - wlen, n, wlen)
        windows = []
        for st in starts:
            lo, hi = max(st, 0), min(st + wlen, n)
            if hi - lo >= max(10, wlen // 2):
                windows.append(lo + jittered_frames(hi - lo, frames_per_window, 1.0, rng))
        if not windows:
            windows = [jittered_frames(n, frames_per_window, 1.0, rng)]
        frames = np.unique(np.concatenate(windows))
        std = distance_std(markers, frames)
        labels, G, vals = spectral_labels(affinity(windowed_spread(markers, windows)), n_groups, seed=seed + s)
        results.append((labels, G, vals, std))
    votes = np.array([r[1] for r in results])
    counts = np.bincount(votes)
    G = int(np.argmax(counts))  # ties go to fewer groups
    best = None
    for labels, g, vals, std in results:
        if g != G:
            continue
        score = within_spread(std, labels)
        if best is None or score < best[0]:
            best = (score, labels, vals, std)
    score, labels, vals, std = best
    return Clustering(labels, int(labels.max() + 1), std, score, vals, votes)
