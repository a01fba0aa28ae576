"""Each sensor's rotation jitter (docs/design.md §3a): where the four-frame windows of its rotation's third
difference start in a take, the histogram their squared norms fill, and the median read off it as noise.

GramAccumulator keeps the counts; the rules live here so every way frames arrive gives the same windows."""

from __future__ import annotations

import numpy as np

# Histogram of log10 of the squared third difference of the frame-to-frame rotation.
LO, HI, BINS = -20.0, 1.0, 210
# A white per-axis jitter s² makes the third difference's squared norm 20 s² × χ²(3); χ²(3)'s median is 2.366.
SCALE = 20.0 * 2.3660
# Four-frame windows: back to back (every frame used, the windows independent) over the take's first DENSE
# frames, so a short take still gives its median enough samples; then one every STRIDE frames, which keeps a
# long take's median current at an eighth of the cost.
DENSE = 4096
STRIDE = 32


def window_starts(first: int, n: int) -> tuple[np.ndarray, int]:
    """(starts, dense): the windows that start in take frames [first, first + n), as offsets from `first`,
    every 4th frame below DENSE and every STRIDE-th after; `dense` counts the back-to-back ones."""
    end = first + n
    dense = np.arange(first + (-first) % 4, min(end, DENSE), 4)
    lo = max(first, DENSE)
    sparse = np.arange(lo + (DENSE - lo) % STRIDE, end, STRIDE)
    return np.concatenate([dense, sparse]) - first, len(dense)


def bin_counts(x: np.ndarray, sel: np.ndarray, m: int) -> np.ndarray:
    """(m, BINS) histogram counts of the squared third differences `x` (q, m) where `sel` (q, m)."""
    with np.errstate(divide="ignore"):
        lg = np.log10(np.maximum(x[sel], 1e-300))
    bins = np.clip(((lg - LO) * (BINS / (HI - LO))).astype(np.intp), 0, BINS - 1)
    sensor = np.nonzero(sel)[1]
    return np.bincount(sensor * BINS + bins, minlength=m * BINS).reshape(m, BINS)


def median_noise(h: np.ndarray) -> np.ndarray:
    """(m,) variance per axis in rad² from each sensor's histogram row, read as white noise: the median window,
    interpolated within its bin; NaN for a sensor with fewer than 8 windows."""
    total = h.sum(axis=1)
    cum = np.cumsum(h, axis=1)
    k = np.argmax(cum >= 0.5 * total[:, None], axis=1)
    below = np.where(k > 0, cum[np.arange(len(k)), k - 1], 0.0)
    inside = h[np.arange(len(k)), k]
    frac = np.where(inside > 0, (0.5 * total - below) / np.where(inside > 0, inside, 1.0), 0.5)
    lg = LO + (k + frac) * ((HI - LO) / BINS)
    return np.where(total >= 8, 10.0 ** lg / SCALE, np.nan)
