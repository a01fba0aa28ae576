"""Real 6-DOF takes from the real optical captures in ../shared/data: each technical cluster's rigid fit
(Kabsch, per frame) is one "sensor", as if a magnetic sensor were strapped to that segment.

The captures sit beside the repository, not in it: CI always has them, a user's clone may not, so
`capture_path` skips the calling test with the reason when they are absent.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from flockcal.takes import Take, make_take

SHARED_DATA = Path(os.environ.get("FLOCKCAL_SHARED_DATA", Path(__file__).resolve().parents[1].parent / "shared" / "data"))
KNEE = "biobuddy_right_knee.c3d"
UPPER_LIMB = "pyomeca_markers_analogs.c3d"


def capture_path(name: str) -> Path:
    """The path of a shared real capture, or skip: the test needs ../shared/data (CI has it)."""
    path = SHARED_DATA / name
    if not path.exists():
        pytest.skip(f"real capture {name} not found in {SHARED_DATA} (set FLOCKCAL_SHARED_DATA or clone beside ../shared)")
    pytest.importorskip("ezc3d", reason="reading C3D needs ezc3d (pip install '.[test]')")
    return path


def segment_map(name: str) -> dict:
    """The capture's entry in segments.json: marker names per segment and each segment's anatomical parent."""
    return json.loads((SHARED_DATA / "segments.json").read_text())[name]


def marker_index(labels, name: str) -> int:
    """Index of the marker the segment map calls `name`: the same label, or the label with the subject
    prefix some files carry ("Daphnee:STER" for "STER"; the box's own "boite:…" names are given whole)."""
    for k, label in enumerate(labels):
        if label == name or label.endswith(":" + name):
            return k
    raise KeyError(f"no marker {name!r} in the capture")


def kabsch(points: np.ndarray, shape: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rigid fit of `shape` (k, 3) onto each frame of `points` (n, k, 3, NaN where unseen): rotations
    (n, 3, 3), positions (n, 3) with points ≈ R shape + t, and valid (n,) where ≥ 3 markers were seen."""
    seen = np.isfinite(points).all(axis=2)
    w = seen.astype(float)
    cnt = np.maximum(w.sum(axis=1), 1.0)
    P = np.where(seen[..., None], points, 0.0)
    S = np.where(seen[..., None], shape[None], 0.0)
    pc = P.sum(axis=1) / cnt[:, None]
    sc = S.sum(axis=1) / cnt[:, None]
    H = np.einsum("nk,nki,nkj->nij", w, P - pc[:, None], S - sc[:, None])
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(U @ Vt))
    D = np.ones((len(points), 3))
    D[:, 2] = np.where(d == 0, 1.0, d)
    R = (U * D[:, None, :]) @ Vt
    t = pc - np.einsum("nij,nj->ni", R, sc)
    return R, t, seen.sum(axis=1) >= 3


def cluster_shape(points: np.ndarray) -> np.ndarray:
    """A cluster's shape in its own frame: the first fully seen frame, refined by averaging every frame
    brought back onto it (one round of generalised Procrustes), centred on its centroid."""
    full = np.flatnonzero(np.isfinite(points).all(axis=(1, 2)))
    if not len(full):
        raise ValueError("the cluster is never fully seen")
    shape = points[full[0]] - points[full[0]].mean(axis=0)
    for _ in range(2):
        R, t, ok = kabsch(points, shape)
        back = np.einsum("nji,nkj->nki", R, points - t[:, None])  # Rᵀ (p − t)
        shape = np.nanmean(back[ok], axis=0)
        shape -= shape.mean(axis=0)
    return shape


def cluster_poses(mt, markers) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-frame rigid poses (R, t, valid) of the named markers of a loaded capture, as one cluster."""
    pts = mt.markers[:, [marker_index(mt.marker_names, x) for x in markers]]
    return kabsch(pts, cluster_shape(pts))


def cluster_take(name: str, clusters: dict | None = None) -> Take:
    """A 6-DOF take of the capture `name`: one sensor per technical cluster (default: the segment map's
    `technical_clusters`, else its segments), frames where a cluster has < 3 markers invalid."""
    from flockcal.markers import load_c3d

    mt = load_c3d(capture_path(name))
    info = segment_map(name)
    clusters = clusters or info.get("technical_clusters") or info["segments"]
    Rs, ts, vs = [], [], []
    for markers in clusters.values():
        R, t, ok = cluster_poses(mt, markers)
        Rs.append(R), ts.append(t), vs.append(ok)
    R, t, v = np.stack(Rs, axis=1), np.stack(ts, axis=1), np.stack(vs, axis=1)
    R = np.where(v[..., None, None], R, np.eye(3))
    t = np.where(v[..., None], t, 0.0)
    return make_take(R, t, list(clusters), mt.rate_hz, valid=v, times=mt.times, source=name)
