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

from flockcal.rotations import as_quat
from flockcal.solver.calibration import Calibration
from flockcal.solver.calibration_json import as_calibration
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

    def __init__(self, art, names: tuple[str, ...], determined: set[str] | None, fit: Calibration):
        from flockcal.exports.bvh import node_names

        self.art = art
        self.rig_names = node_names(fit, names)  # the rig's node names (the glTF's)
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


def _determined(cal: Calibration) -> set[str] | None:
    """The children of the fit's determined joints; None for a saved skeleton, whose bones are known
    whatever this take has pinned yet."""
    if cal.known_skeleton:
        return None
    return {cal.names[int(c)] for c, d in zip(cal.joint_child, cal.joints.determined) if d}


def _layout(fit: Calibration | dict, names: tuple[str, ...]) -> _Layout | None:
    if _cache[0] is fit and _cache[1] == names:
        return _cache[2]
    try:
        cal = as_calibration(fit, error=ArticulationError)  # a §5 dict (a truth file) is decoded once, here
        layout = _Layout(articulation(cal).reordered(names), names, _determined(cal), cal)
    except (ArticulationError, KeyError, ValueError, TypeError):
        layout = None
    _cache[:] = [fit, names, layout]
    return layout


def live_pose(names, rotations, positions, valid, fit: Calibration | dict | None,
              fit_id: tuple[str, int | None] | None = None) -> dict:
    """Pose message body for one frame: (m,3,3) rotations, (m,3) positions, (m,) valid; fit = the live
    service's Calibration, or a §5 dict (a truth file: decoded once by `calibration_from_json`); fit_id =
    (session id, fit_seq) of that fit, fit_seq None for a stopped session's stored fit (the rig's `session`
    and `fit_seq`).

    joints: one point per tree joint (named by its child body; `determined` false for one the data do not
    pin yet), one for the root sensor and one for each leaf's sensor (so end bones have a far end); bones:
    index pairs into joints, none ending at an undetermined joint; sensors: measured position and row-major
    rotation (body → world) of each sensor.
    """
    base = sensors_only(names, rotations, positions, valid)
    if fit is None:
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
    joints = [{"name": n, "kind": k, "p": p, "determined": d} for (n, k, d), p in zip(layout.heads, at)]
    return {**base, "joints": joints, "bones": layout.bones, "root": layout.root, "rig": rig_pose(rec, layout, fit_id)}


def rig_pose(rec, layout: _Layout, fit_id: tuple[str, int | None] | None = None) -> dict:
    """The frame as the glTF rig plays it with rest "sensor" (node axes = sensor axes, so no rest frame
    to carry): node name → local rotation [x, y, z, w] (child: R_pᵀ R_j; root: W R_root, as
    exports/bvh.local_rotations with A = I), and the root node's translation W t_root, metres, Y-up
    (the same numbers `/gltf?rest=sensor` keys its animation with); with `fit_id`, whose fit it is."""
    from flockcal.exports.bvh import bvh_world

    art = layout.art
    world = bvh_world(RIG_UP)
    R = rec.rotations[0]
    local = np.swapaxes(R[np.maximum(art.parent, 0)], -1, -2) @ R
    local[art.root] = world @ R[art.root]
    q = np.round(as_quat(local, scalar_first=False), 7).tolist()
    root = _round(world @ rec.joint_positions[0, art.root], 6)
    rig = {"up": RIG_UP, "rest": "sensor", "root": root, "rotations": dict(zip(layout.rig_names, q))}
    if fit_id is None:
        return rig
    session, fit_seq = fit_id
    return {**rig, "session": session, "fit_seq": fit_seq}
