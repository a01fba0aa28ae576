"""The live skeleton a browser draws: joint world positions with the residual removed (paper §3.4).

Each body is placed from its parent's pose, starting at the root sensor, so bones never stretch; the
message holds plain points, index pairs and sensor poses so the page needs no math of its own.
"""

from __future__ import annotations

import numpy as np

from flockcal.solver.reconstruct import ArticulationError, articulation, reconstruct


def _round(a, nd: int = 5):
    return np.round(np.asarray(a, dtype=float), nd).tolist()


def sensors_only(names, rotations, positions, valid) -> dict:
    """Pose with no fit yet: only where the sensors are (as measured)."""
    # Round and convert whole arrays at once: this runs for every pose message.
    p = _round(positions)
    R = _round(np.asarray(rotations).reshape(-1, 9))
    v = np.asarray(valid, dtype=bool).tolist()
    return {
        "joints": [],
        "bones": [],
        "sensors": [{"name": n, "p": p[i], "R": R[i], "valid": v[i]} for i, n in enumerate(names)],
    }


_cache: list = [None, None, None]  # (fit, names, articulation): a fit changes ~30 times/s, poses more often


def _articulation(fit: dict, names: tuple[str, ...]):
    if _cache[0] is fit and _cache[1] == names:
        return _cache[2]
    try:
        art = articulation(fit).reordered(names)
    except (ArticulationError, KeyError, ValueError, TypeError):
        art = None
    _cache[:] = [fit, names, art]
    return art


def live_pose(names, rotations, positions, valid, fit: dict | None) -> dict:
    """Pose message body for one frame: (m,3,3) rotations, (m,3) positions, (m,) valid; fit = §5 dict.

    joints: one point per tree joint (named by its child body), one for the root sensor and one for
    each leaf's sensor (so end bones have a far end); bones: index pairs into joints; sensors: measured
    position and row-major rotation (body → world) of each sensor.
    """
    base = sensors_only(names, rotations, positions, valid)
    if not fit or not fit.get("parent"):
        return base
    art = _articulation(fit, tuple(names))
    if art is None:
        return base
    try:
        # The rotations are each sensor's newest valid pose (held through dropouts), so use them all.
        rec = reconstruct(rotations[None], positions[None], art)
    except (ArticulationError, ValueError):
        return base
    pivots = _round(rec.joint_positions[0])  # inboard joint of each body, root sensor at the root
    sensor_at = _round(rec.sensor_positions[0])
    m = len(names)
    root = art.root
    points = []
    index = {}
    for i in range(m):
        index[i] = len(points)
        kind = "root" if i == root else "joint"
        points.append({"name": names[i], "kind": kind, "p": pivots[i]})
    bones = []
    has_child = np.zeros(m, dtype=bool)
    for j in range(m):
        p = int(art.parent[j])
        if p >= 0:
            has_child[p] = True
            bones.append([index[p], index[j]])
    for j in range(m):
        if j != root and not has_child[j]:
            # A leaf (hand, foot, head) ends at its sensor: draw the bone out to it.
            points.append({"name": f"{names[j]} sensor", "kind": "end", "p": sensor_at[j]})
            bones.append([index[j], len(points) - 1])
    base["joints"] = points
    base["bones"] = bones
    base["root"] = names[root]
    return base
