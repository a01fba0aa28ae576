"""Whether a take's markers sit fixed on their bodies: each body's marker-to-marker distances vary no more
than the markers' own frame-to-frame noise explains. Skin slides a marker smoothly with the joints' angles;
noise is white; the fourth differences of a distance see the noise and not the slide (nor the motion: a
distance does not move with the body).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# A distance varies beyond its noise when the ratio of its variance to the noise's exceeds 1 by more than
# z of its standard errors. On white Gaussian noise that ratio (both variances read by medians of absolute
# deviations) has a standard deviation of RATIO_SD / √frames (3.2–3.4 measured over 480–4000 frames,
# tests/test_optical_fixed_markers.py; on the simulated takes' 651 pairs of markers on one bone, 1.00 of it).
# z is set so that a take of fixed markers is read as sliding once in FALSE_ALARM takes, whatever the number
# of tests (bodies, or pairs of markers) it makes: Bonferroni's bound on the normal tail.
RATIO_SD = 3.3
FALSE_ALARM = 1e-3


def beyond_noise_z(tests: int) -> float:
    """The standard errors a ratio may exceed 1 by in each of `tests` tests (FALSE_ALARM over them all)."""
    from statistics import NormalDist

    return NormalDist().inv_cdf(1.0 - FALSE_ALARM / max(int(tests), 1))

# Var(Δ⁴x) = 70 σ² for white noise of variance σ² (the binomial coefficients 1, 4, 6, 4, 1 squared and summed).
FOURTH_DIFFERENCE_GAIN = 70.0

# Consecutive frames the noise is read on at most: runs spread over the take, enough for a robust scale
# (4000: a ratio known to ±0.05).
NOISE_FRAMES = 4000
NOISE_RUNS = 20

MAD_TO_SD = 1.4826


@dataclass(frozen=True)
class MarkerNoise:
    """The markers' white noise and each body's distance spread over it."""

    sigma_m: float  # white noise of one marker, per coordinate (m): median over the bodies' marker pairs
    ratio: np.ndarray  # (G,) variance of each body's marker distances over what their white noise gives; NaN: one marker
    spread_m: np.ndarray  # (G,) robust standard deviation of each body's marker distances (m), pooled over its pairs
    limit: np.ndarray  # (G,) the ratio a body of fixed markers stays under (`beyond_noise_z` standard errors over 1)

    @property
    def fixed(self) -> np.ndarray:
        """(G,) bool: the body keeps its marker distances within their noise (a body of one marker: False)."""
        return np.isfinite(self.ratio) & (self.ratio <= self.limit)

    @property
    def rigid(self) -> bool:
        """Every body of two or more markers keeps its distances within their noise."""
        judged = np.isfinite(self.ratio)
        return bool(judged.any() and self.fixed[judged].all())


def noise_frames(n: int, total: int = NOISE_FRAMES, runs: int = NOISE_RUNS) -> np.ndarray:
    """Up to `total` frame indices in `runs` runs of consecutive frames spread over n frames."""
    if n <= total:
        return np.arange(n)
    length = total // runs
    starts = np.linspace(0, n - length, runs).astype(int)
    return (starts[:, None] + np.arange(length)[None]).ravel()


def white_sd(x: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """Robust standard deviation of the white noise in each column of x (f, s), from its fourth differences
    over runs of five consecutive frames (`frames` the frame index of each row; a gap or a jump between runs
    leaves no difference there); NaN where no run of five was seen."""
    d = x
    for _ in range(4):
        d = d[1:] - d[:-1]
    consecutive = frames[4:] - frames[:-4] == 4
    d = np.where(consecutive[:, None], d, np.nan)
    return MAD_TO_SD * nan_mad(d) / np.sqrt(FOURTH_DIFFERENCE_GAIN)


def nan_median(x: np.ndarray) -> np.ndarray:
    """Median of each column of x (f, s), ignoring NaN (NaN where all are): one sort, NaN last (numpy's
    nanmedian goes column by column)."""
    y = np.sort(x, axis=0)
    n = np.isfinite(y).sum(0)
    lo = np.take_along_axis(y, np.maximum((n - 1) // 2, 0)[None], axis=0)[0]
    hi = np.take_along_axis(y, np.maximum(n // 2, 0)[None], axis=0)[0]
    return np.where(n > 0, 0.5 * (lo + hi), np.nan)


def nan_mad(x: np.ndarray) -> np.ndarray:
    """Median absolute deviation of each column from its median, ignoring NaN (NaN where all are)."""
    return nan_median(np.abs(x - nan_median(x)))


def marker_noise(markers: np.ndarray, groups: list[np.ndarray]) -> MarkerNoise:
    """The white noise of the markers (n, k, 3) and, per body of `groups`, how far its marker-to-marker
    distances vary beyond it. Robust scales throughout (medians of absolute deviations): a label swap or a
    glitch over a few percent of the frames moves neither."""
    frames = noise_frames(len(markers))
    M = markers[frames]
    G = len(groups)
    ratio = np.full(G, np.nan)
    spread = np.full(G, np.nan)
    limit = np.full(G, np.nan)
    z = beyond_noise_z(sum(len(idx) >= 2 for idx in groups))
    whites = []
    for g, idx in enumerate(groups):
        if len(idx) < 2:
            continue
        a, b = np.triu_indices(len(idx), 1)
        d = np.linalg.norm(M[:, idx[a]] - M[:, idx[b]], axis=-1)  # (f, pairs)
        s = MAD_TO_SD * nan_mad(d)
        w = white_sd(d, frames)
        ok = np.isfinite(s) & np.isfinite(w)
        if not ok.any():
            continue
        spread[g] = float(np.sqrt(np.mean(s[ok] ** 2)))
        white2 = float(np.mean(w[ok] ** 2))
        # Exact distances (a noise-free simulation) are rigid however small their noise.
        ratio[g] = spread[g] ** 2 / white2 if white2 > 0 else (0.0 if spread[g] < 1e-9 else np.inf)
        frames_seen = float(np.median(np.isfinite(d[:, ok]).sum(0)))
        limit[g] = 1.0 + z * RATIO_SD / np.sqrt(max(frames_seen, 1.0))
        whites.append(w[ok])
    # A distance carries the noise of two markers, each seen along the line between them: 2σ².
    sigma = float(np.median(np.concatenate(whites)) / np.sqrt(2.0)) if whites else float("nan")
    return MarkerNoise(sigma, ratio, spread, limit)


# A distance this many of its noise's standard deviations from its median is a label swap or a glitch in
# that frame (a fixed marker's distances move by its noise alone: 1 in 10⁶ frames at 5).
OUTLIER_SD = 5.0


def blank_off_shape(markers: np.ndarray, groups: list[np.ndarray], sigma_m: float) -> np.ndarray:
    """The markers (n, k, 3) with the marker-frames blanked that left their body's shape: a distance off its
    median by more than OUTLIER_SD noise standard deviations (√2 σ a distance) is a swapped label or a glitch
    at one of its two ends. The end blamed is the marker whose distances moved most in all, when every such
    distance of the frame runs to it (an honest marker keeps its distances to the other honest ones; a swap
    with a marker close by moves some of its distances by less than the limit); otherwise every marker at
    the end of one. Of a body of two markers, both go."""
    out = markers.copy()
    limit = OUTLIER_SD * np.sqrt(2.0) * sigma_m
    if not np.isfinite(limit):
        return out
    for idx in groups:
        q = len(idx)
        if q < 2:
            continue
        a, b = np.triu_indices(q, 1)
        d = np.linalg.norm(markers[:, idx[a]] - markers[:, idx[b]], axis=-1)
        with np.errstate(all="ignore"):
            dev = np.abs(d - nan_median(d))
        off = np.isfinite(dev) & (dev > limit)  # (n, pairs)
        inc = np.zeros((len(a), q))
        inc[np.arange(len(a)), a] = inc[np.arange(len(a)), b] = 1.0
        moved = np.nan_to_num(dev) @ inc  # (n, q) each marker's distances' deviation in all
        worst = np.argmax(moved, axis=1)
        on_worst = inc[:, worst].T.astype(bool)  # (n, pairs): the pair runs to the worst marker
        single = (off <= on_worst).all(1) & (q > 2)
        blame = np.where(single[:, None], np.eye(q, dtype=bool)[worst], (off.astype(float) @ inc) > 0)
        blame &= off.any(1)[:, None]
        out[:, idx] = np.where(blame[..., None], np.nan, out[:, idx])
    return out


def fixed_labels(markers: np.ndarray, candidates: np.ndarray | None = None) -> np.ndarray | None:
    """(k,) body of each marker, for markers fixed on their bodies: two markers ride one body when their
    distance varies within its noise (as `marker_noise` judges a body), and the bodies are the groups in
    which every pair does so; None when the pairs do not fall into such groups (a marker within noise of two
    markers that are not of each other: skin, or a joint that did not move). `candidates` (k, k) bool: the
    pairs worth testing (default all; the others ride different bodies)."""
    frames = noise_frames(len(markers))
    M = markers[frames]
    k = M.shape[1]
    a, b = np.triu_indices(k, 1)
    z = beyond_noise_z(len(a))
    if candidates is not None:
        keep = candidates[a, b]
        a, b = a[keep], b[keep]
    d = np.linalg.norm(M[:, a] - M[:, b], axis=-1)
    s, w = MAD_TO_SD * nan_mad(d), white_sd(d, frames)
    count = np.isfinite(d).sum(0)
    with np.errstate(all="ignore"):
        close = (s**2 <= w**2 * (1.0 + z * RATIO_SD / np.sqrt(np.maximum(count, 1)))) & (count > 0)
    adj = np.zeros((k, k), dtype=bool)
    adj[a[close], b[close]] = adj[b[close], a[close]] = True
    labels = np.full(k, -1)
    for i in range(k):
        if labels[i] >= 0:
            continue
        group = np.union1d([i], np.flatnonzero(adj[i]))
        if not (adj[np.ix_(group, group)] | np.eye(len(group), dtype=bool)).all() or (labels[group] >= 0).any():
            return None
        labels[group] = labels.max() + 1
    return labels
