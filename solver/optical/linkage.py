"""Average linkage (UPGMA) over the inter-marker distance ranges: the first grouping of markers into bodies
that the segmentation (solver/optical/segmentation.py) then judges by how the groups move.
"""

from __future__ import annotations

import numpy as np


def linkage_matrix(ranges: np.ndarray, tolerance: float) -> np.ndarray:
    """The distance ranges as average linkage starts from them: pairs never seen together far beyond any
    merge (10 × the largest range or the tolerance), the diagonal closed."""
    finite = np.isfinite(ranges)
    big = 10.0 * max(float(ranges[finite].max()) if finite.any() else 1.0, tolerance)
    D = np.where(finite, ranges, big).astype(float)
    np.fill_diagonal(D, np.inf)
    return D


def linkage_labels(ranges: np.ndarray, tolerance: float, n_groups: int | None = None) -> np.ndarray:
    """Average-linkage (UPGMA) clusters of the distance ranges, merged while the closest two clusters'
    mean range is within `tolerance` (or until `n_groups` remain).

    Average linkage, not single: markers near a joint keep their distance to the other segment's markers
    nearly constant, so one such pair must not join two segments; the mean over all pairs does not care.
    Written out (k − 1 merges of a k × k matrix) rather than taken from scipy.cluster, whose import alone
    costs a third of the time budget of a small take."""
    k = len(ranges)
    D = linkage_matrix(ranges, tolerance)
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
