"""Hinges among markers fixed on their bones: whether two bodies' relative rotation turned beyond its noise
about one axis only (`relative_hinge`), for the bundle (`joint_bundle`: a hinge's point along its axis is
held, not fitted) and for the tree's joints once posed (`hinge_slides`: the point placed on the axis by
design.md §3c's rule).
"""

from __future__ import annotations

import numpy as np

# A hinge turns beyond its noise about one axis only: about the other two its relative rotation's variance is
# the white noise's (a ratio of 1, known to a few per cent over a take). Over 36 simulated takes of fixed
# markers (walk, kiosk, exercise, seeds 0–11) the hinges' other axes came out at 0.94–1.54 and the balls' at
# 2.3 and more (an ankle the walk barely turned sideways); the design's ×4 (design.md §3a) would have called
# four of those ankles hinges. Twice the noise's variance, between the two.
HINGE_MARGIN = 2.0


def relative_hinge(Ra: np.ndarray, oka: np.ndarray, Rb: np.ndarray, okb: np.ndarray):
    """(hinge, axis in a's frame, axis in b's frame; NaN unless a hinge) for two bodies posed Ra, Rb
    (n, 3, 3) on consecutive frames (where oka, okb): their relative rotation beyond its noise
    (ROTATION_MARGIN in variance, as `articulation.judge` reads it) about one axis only. The noise is the
    relative rotation's own white part, read from its fourth differences over five consecutive frames
    (`marker_noise`): with fixed markers the poses' noise is white and their motion smooth."""
    from flockcal.solver.optical.articulation import ROTATION_MARGIN
    from flockcal.solver.optical.marker_noise import FOURTH_DIFFERENCE_GAIN

    none = (False, np.full(3, np.nan), np.full(3, np.nan))
    idx = np.flatnonzero(oka & okb)
    run = idx[4:] - idx[:-4] == 4  # five consecutive frames
    if run.sum() < 20:
        return none
    Q = Ra[idx].transpose(0, 2, 1) @ Rb[idx]  # b in a's frame
    U, _, Vt = np.linalg.svd(Q.mean(0))
    Qm = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    E = Q @ Qm.T
    w = 0.5 * np.stack([E[:, 2, 1] - E[:, 1, 2], E[:, 0, 2] - E[:, 2, 0], E[:, 1, 0] - E[:, 0, 1]], axis=1)
    spread, V = np.linalg.eigh(np.cov(w.T))
    # Along each of the turn's principal directions: its variance over the white noise's there, both mean
    # powers over the frames (a frame with a marker hidden turns more, in the spread and in the noise).
    u = w @ V
    d4 = u[4:] - 4 * u[3:-1] + 6 * u[2:-2] - 4 * u[1:-3] + u[:-4]
    noise = (d4[run] ** 2).mean(0) / FOURTH_DIFFERENCE_GAIN
    lam = spread / np.maximum(noise, 1e-30)
    if lam[2] < ROTATION_MARGIN or max(lam[0], lam[1]) >= HINGE_MARGIN:
        return none
    axis = V[:, 2]  # the rotation vectors' one direction: the axis, a's frame
    return True, axis, Qm.T @ axis


def marker_hinges(markers: np.ndarray, shapes, pairs: np.ndarray, rotations: np.ndarray, valid: np.ndarray):
    """For each tree joint (child, parent) in `pairs`: whether it is a hinge, and its axis in the child's and
    the parent's shape frame (NaN elsewhere), by `relative_hinge`. A body of three markers or more is posed
    from its markers alone, one of fewer by `rotations` (its markers and joints)."""
    from flockcal.solver.optical.rigid import rigid_fit

    P = len(pairs)
    hinge = np.zeros(P, dtype=bool)
    ax_c, ax_p = np.full((P, 3), np.nan), np.full((P, 3), np.nan)
    poses: dict = {}

    def pose(g):
        if g not in poses:
            sh = shapes[g]
            poses[g] = rigid_fit(sh.marker_offsets, markers[:, sh.markers])[::2] if len(sh.markers) >= 3 \
                else (rotations[:, g], valid[:, g])
        return poses[g]

    for i, (c, p) in enumerate(pairs):
        (Ra, oka), (Rb, okb) = pose(int(c)), pose(int(p))
        hinge[i], ax_c[i], ax_p[i] = relative_hinge(Ra, oka, Rb, okb)
    return hinge, ax_c, ax_p


def hinge_slides(markers: np.ndarray, shapes, parent: np.ndarray, rotations: np.ndarray, valid: np.ndarray,
                 points: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
    """The tree joints' points with each hinge (`marker_hinges`) slid along its axis to design.md §3c's point
    (the sensor path's rule, `hinge_point.hinge_offsets`: where the limb's bones meet the axis); the other
    joints as they are."""
    from flockcal.solver.hinge_point import hinge_offsets

    kids = [int(c) for c in np.flatnonzero(parent >= 0)]
    if not kids:
        return points
    pairs = np.array([(c, int(parent[c])) for c in kids])
    hinge, ax_c, ax_p = marker_hinges(markers, shapes, pairs, rotations, valid)
    c = np.array([shapes[k].joint_offsets[shapes[k].joints.index(k)] for k in kids])
    l = np.array([shapes[int(parent[k])].joint_offsets[shapes[int(parent[k])].joints.index(k)] for k in kids])
    s, how, _ = hinge_offsets(pairs, c, l, ax_c, ax_p, hinge, np.ones(len(kids), dtype=bool))
    out = dict(points)
    for i, k in enumerate(kids):
        if how[i] >= 0 and s[i] != 0 and k in out:
            axis = np.einsum("nij,j->ni", rotations[:, k], ax_c[i])
            out[k] = np.where(valid[:, k, None], out[k] + s[i] * axis, out[k])
    return out
