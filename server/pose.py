"""The live skeleton a browser draws: joint world positions with the residual removed (paper §3.4).

Each body is placed from its parent's pose, starting at the root sensor, so bones never stretch; the
message holds plain points, index pairs and sensor poses so the page needs no math of its own. As in the
solver's bones, only determined joints end a bone (design.md §3a): an undetermined one is still placed
(its children hang from it) but drawn as a point, not joined. With a fit it also carries `rig`: each
body's local rotation as a quaternion in the glTF rig's frame (exports/gltf.py, rest "sensor") and the
root's position, so an engine that loaded `/gltf?rest=sensor` sets its nodes with no maths, and whose fit
drew it (`session`, `fit_seq`), so a page knows which rig the stream drives.
"""

from __future__ import annotations

import numpy as np

from flockcal.solver.calibration import Calibration
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


# The live rig's frame: the Flock's world (+Z down) turned Y-up, as the /gltf download's default `up`.
RIG_UP = "-z"


class _Layout:
    """What a fit fixes about the drawing: the articulation, point names and kinds, bones, leaves."""

    def __init__(self, art, names: tuple[str, ...], determined: set[str] | None = None, fit=None):
        from flockcal.exports.bvh import node_names

        self.art = art
        self.rig_names = node_names(fit if fit is not None else art, names)  # the rig's node names (the glTF's)
        art.levels  # worked out once here; the per-frame completed copies of `art` inherit it
        m = len(names)
        root = art.root
        has_child = np.zeros(m, dtype=bool)
        has_child[art.parent[art.parent >= 0]] = True
        self.leaves = [j for j in range(m) if j != root and not has_child[j]]
        # A body's pivot is a measured point at the root (its sensor) or at a determined joint.
        ok = [i == root or determined is None or names[i] in determined for i in range(m)]
        # Points: every body's pivot (index = body), then the far end of each leaf bone at its sensor.
        self.heads = [(names[i], "root" if i == root else "joint", ok[i]) for i in range(m)]
        self.heads += [(f"{names[j]} sensor", "end", True) for j in self.leaves]
        self.bones = [[int(art.parent[j]), j] for j in range(m) if art.parent[j] >= 0 and ok[j] and ok[art.parent[j]]]
        self.bones += [[j, m + k] for k, j in enumerate(self.leaves) if ok[j]]
        self.root = names[root]


_cache: list = [None, None, None]  # (fit, names, layout): a fit changes ~30 times/s, poses more often


def _determined(fit: Calibration | dict) -> set[str] | None:
    """The children of the fit's determined joints; None for a saved skeleton, whose bones are known
    whatever this take has pinned yet."""
    if isinstance(fit, Calibration):
        if fit.known_skeleton:
            return None
        return {fit.names[int(c)] for c, d in zip(fit.joint_child, fit.joints.determined) if d}
    if fit.get("known_skeleton"):
        return None
    # Joints of stored fits made before "determined" existed count as determined.
    return {j["child"] for j in fit.get("joints") or [] if j.get("determined", True)}


def _layout(fit: Calibration | dict, names: tuple[str, ...]) -> _Layout | None:
    if _cache[0] is fit and _cache[1] == names:
        return _cache[2]
    try:
        layout = _Layout(articulation(fit).reordered(names), names, _determined(fit), fit)
    except (ArticulationError, KeyError, ValueError, TypeError):
        layout = None
    _cache[:] = [fit, names, layout]
    return layout


def live_pose(names, rotations, positions, valid, fit: Calibration | dict | None,
              fit_id: tuple[str, int | None] | None = None) -> dict:
    """Pose message body for one frame: (m,3,3) rotations, (m,3) positions, (m,) valid; fit = the live
    service's Calibration, or a §5 dict (a stored result, a truth file); fit_id = (session id, fit_seq)
    of that fit, fit_seq None for a stopped session's stored fit (the rig's `session` and `fit_seq`).

    joints: one point per tree joint (named by its child body; `determined` false for one the data do not
    pin yet), one for the root sensor and one for each leaf's sensor (so end bones have a far end); bones:
    index pairs into joints, none ending at an undetermined joint; sensors: measured position and row-major
    rotation (body → world) of each sensor.
    """
    base = sensors_only(names, rotations, positions, valid)
    if fit is None or (isinstance(fit, dict) and not fit.get("parent")):
        return base
    layout = _layout(fit, tuple(names))
    if layout is None:
        return base
    try:
        # The rotations are each sensor's newest valid pose (held through dropouts), so use them all.
        rec = reconstruct(rotations[None], positions[None], layout.art)
    except (ArticulationError, ValueError):
        return base
    # Pivots (inboard joint of each body, root sensor at the root), then the leaves' sensors.
    at = _round(np.concatenate([rec.joint_positions[0], rec.sensor_positions[0, layout.leaves]]))
    base["joints"] = [{"name": n, "kind": k, "p": p, "determined": d} for (n, k, d), p in zip(layout.heads, at)]
    base["bones"] = layout.bones
    base["root"] = layout.root
    base["rig"] = rig_pose(rec, layout)
    if fit_id is not None:
        base["rig"]["session"], base["rig"]["fit_seq"] = fit_id
    return base


def rig_pose(rec, layout: _Layout) -> dict:
    """The frame as the glTF rig plays it with rest "sensor" (node axes = sensor axes, so no rest frame
    to carry): node name → local rotation [x, y, z, w] (child: R_pᵀ R_j; root: W R_root, as
    exports/bvh.local_rotations with A = I), and the root node's translation W t_root, metres, Y-up
    (the same numbers `/gltf?rest=sensor` keys its animation with)."""
    from flockcal.exports.bvh import bvh_world

    art = layout.art
    world = bvh_world(RIG_UP)
    R = rec.rotations[0]
    local = np.swapaxes(R[np.maximum(art.parent, 0)], -1, -2) @ R
    local[art.root] = world @ R[art.root]
    q = np.round(quaternions(local), 7).tolist()
    root = _round(world @ rec.joint_positions[0, art.root], 6)
    return {"up": RIG_UP, "rest": "sensor", "root": root, "rotations": dict(zip(layout.rig_names, q))}


# Shepperd's four forms of a rotation's quaternion (x, y, z, w), each 4× the quaternion times one of its
# components, as weights on (1, r00, r01, r02, r10, r11, r12, r20, r21, r22): row 4i + c is form i's
# component c. Form i is the one whose own component i (4 q_i² > 0) is largest: forms x, y, z, w.
_FORMS = np.array([
    # form x: 1 + r00 − r11 − r22, r01 + r10, r02 + r20, r21 − r12
    [1, 1, 0, 0, 0, -1, 0, 0, 0, -1], [0, 0, 1, 0, 1, 0, 0, 0, 0, 0], [0, 0, 0, 1, 0, 0, 0, 1, 0, 0],
    [0, 0, 0, 0, 0, 0, -1, 0, 1, 0],
    # form y: r01 + r10, 1 − r00 + r11 − r22, r12 + r21, r02 − r20
    [0, 0, 1, 0, 1, 0, 0, 0, 0, 0], [1, -1, 0, 0, 0, 1, 0, 0, 0, -1], [0, 0, 0, 0, 0, 0, 1, 0, 1, 0],
    [0, 0, 0, 1, 0, 0, 0, -1, 0, 0],
    # form z: r02 + r20, r12 + r21, 1 − r00 − r11 + r22, r10 − r01
    [0, 0, 0, 1, 0, 0, 0, 1, 0, 0], [0, 0, 0, 0, 0, 0, 1, 0, 1, 0], [1, -1, 0, 0, 0, -1, 0, 0, 0, 1],
    [0, 0, -1, 0, 1, 0, 0, 0, 0, 0],
    # form w: r21 − r12, r02 − r20, r10 − r01, 1 + r00 + r11 + r22
    [0, 0, 0, 0, 0, 0, -1, 0, 1, 0], [0, 0, 0, 1, 0, 0, 0, -1, 0, 0], [0, 0, -1, 0, 1, 0, 0, 0, 0, 0],
    [1, 1, 0, 0, 0, 1, 0, 0, 0, 1],
], dtype=float).T


def quaternions(R: np.ndarray) -> np.ndarray:
    """(m, 4) unit quaternions x, y, z, w of rotation matrices (m, 3, 3), by the largest of w², x², y², z²
    (Shepperd's rule, numerically safe at every angle; the chosen component positive). All four forms come
    out of one product with `_FORMS`: scipy's Rotation.from_matrix costs about 40 µs a matrix here, and the
    rule's masked steps 110 µs for 16 matrices, which the live streams pay up to 144 times a second."""
    R = np.asarray(R, dtype=float).reshape(-1, 9)
    forms = (R @ _FORMS[1:] + _FORMS[0]).reshape(-1, 4, 4)
    rows = _ROWS[:len(R)] if len(R) <= len(_ROWS) else np.arange(len(R))
    q = forms[rows, forms[:, _DIAGONAL, _DIAGONAL].argmax(axis=1)]
    return q / np.sqrt(np.einsum("ij,ij->i", q, q))[:, None]


_DIAGONAL = np.arange(4)
_ROWS = np.arange(1024)  # row numbers made once: a live frame's matrices are a few dozen
