"""The route for markers fixed on their bones (every body keeps its marker distances within the markers'
noise: `marker_noise`): the tree from Kirk's residual of every pair of bodies, the joints from Kirk's fit
where both bodies have a frame of their own and from the bundle of poses and offsets around a body of one or
two markers (`joint_bundle`), a hinge's point on its axis by design.md §3c's rule (`solver/hinge_point.py`).

With no skin, Kirk's distances are the sharpest evidence there is: a pose read from three markers close
together turns with their noise, and a joint placed through it moves by that turn times the lever (7 mm of
scatter at a hip from a thigh's three markers under 1 mm of noise), while a distance carries the noise once.
"""

from __future__ import annotations

import numpy as np

from flockcal.solver.optical.joint_bundle import bundle_joint_points, bundles
from flockcal.solver.optical.kirk_batch import pair_rms, tree_joint_points
from flockcal.solver.optical.marker_noise import MarkerNoise, blank_off_shape, fixed_labels, marker_noise

# A pair is a candidate joint when Kirk's residual is within this many times the markers' noise: a true
# joint's residual is the noise itself (less what the fit takes), and twice it is the design's ×4 margin on
# a variance (design.md §3a).
NOISE_MULTIPLE = 2.0

# Frames the bundle is adjusted on at most, spread over the take: its offsets are means over frames, and each
# frame costs a (6 bodies)² solve per step. A joint pins its centre only in the frames where it turns: the
# exercise routine turns each joint in a slot of about 2 s of its 30, where 300 frames leave some 20 and a
# simulated elbow came 3.4 mm off along the forearm; 1000 leave 66, and it came within 0.9 mm.
BUNDLE_FRAMES = 1000

# Kirk's penalty on the radii (joints.py: 1e-5) keeps a hinge's point from drifting along its axis, and pulls
# a ball's centre towards the markers along the direction the take turned least by as much as 4–5 mm (a hip
# in a walk). Here a hundredth of it: hinges are placed afterwards by the rule (`hinge_slides`).
FIXED_PENALTY = 1e-7

# A hinge turns beyond its noise about one axis only: about the other two its relative rotation's variance is
# the white noise's (a ratio of 1, known to a few per cent over a take). Over 36 simulated takes of fixed
# markers (walk, kiosk, exercise, seeds 0–11) the hinges' other axes came out at 0.94–1.54 and the balls' at
# 2.3 and more (an ankle the walk barely turned sideways); the design's ×4 (design.md §3a) would have called
# four of those ankles hinges. Twice the noise's variance, between the two.
HINGE_MARGIN = 2.0


def fixed_segmentation(markers: np.ndarray, tolerance: float):
    """The bodies of markers fixed on their bones (`marker_noise.fixed_labels`: every pair of a body keeps
    its distance within its noise) as a `Segmentation`, or None: when the pairs do not fall into such bodies,
    or leave a marker alone (skin sliding beyond the noise breaks a body into pieces, single markers among
    them; a body of one marker goes by the general segmentation, as under skin)."""
    from flockcal.solver.optical.segmentation import (
        SEGMENT_FRAMES, Segmentation, canonical, distance_ranges, judging_frames, quantile_range,
    )  # fmt: skip

    frames = judging_frames(len(markers))
    few = frames[np.unique(np.linspace(0, len(frames) - 1, min(len(frames), SEGMENT_FRAMES)).round().astype(int))]
    ranges = distance_ranges(markers[few])
    # Only pairs that stay within what skin moves can ride one body: the noise is read on those alone. Their
    # middle half, not the 10–90 % range: a label swap can fill a tenth of these frames (they come in runs).
    d = np.linalg.norm(markers[few][:, :, None] - markers[few][:, None], axis=-1)
    labels = fixed_labels(markers, candidates=quantile_range(d, low=0.25, high=0.75) <= tolerance)
    if labels is None or (np.bincount(labels) < 2).any():
        return None
    labels = canonical(labels)
    if not marker_noise(markers, [np.flatnonzero(labels == g) for g in range(labels.max() + 1)]).rigid:
        return None
    G = int(labels.max()) + 1
    internal = np.array([np.nanmean(ranges[np.ix_(g, g)][~np.eye(len(g), dtype=bool)])
                         for g in (np.flatnonzero(labels == b) for b in range(G))])
    return Segmentation(labels, G, float(tolerance), ranges, internal, few, labels.copy(), ())


def fixed_costs(markers: np.ndarray, groups: list[np.ndarray], noise: MarkerNoise, frames: np.ndarray) -> np.ndarray:
    """(G, G) Kirk's residual rms of every pair of bodies of two or more markers on `frames`, over the
    markers' noise; inf where over NOISE_MULTIPLE (no joint) or a body has one marker (no orientation).
    Swapped labels and glitches are blanked first (`blank_off_shape`)."""
    G = len(groups)
    cost = np.full((G, G), np.inf)
    big = [g for g in range(G) if len(groups[g]) >= 2]
    pairs = np.array([(a, b) for i, a in enumerate(big) for b in big[i + 1:]], dtype=int).reshape(-1, 2)
    if not len(pairs):
        return cost
    clean = blank_off_shape(markers, groups, noise.sigma_m)
    rms = pair_rms(clean, groups, pairs, frames) / max(noise.sigma_m, 1e-12)
    rms = np.where(rms <= NOISE_MULTIPLE, rms, np.inf)
    cost[pairs[:, 0], pairs[:, 1]] = cost[pairs[:, 1], pairs[:, 0]] = rms
    return cost


def fixed_joint_points(markers: np.ndarray, groups: list[np.ndarray], parent: np.ndarray, frames: np.ndarray | None,
                       noise: MarkerNoise, only=None):
    """({child: (n, 3) joint centre per frame}, {child: residual rms (m)}, {child: (n, q) residuals of the
    joint's markers, the child's then the parent's}) for the tree joints (those in `only`, and every joint
    fitted together with one of them; default all): Kirk's fit, all joints at once on `frames` (default all
    frames); then, around each body of fewer than three markers, the bundle's. Marker-frames off their body's
    shape beyond the noise (swapped labels, glitches) are left out (`blank_off_shape`)."""
    n = len(markers)
    markers = blank_off_shape(markers, groups, noise.sigma_m)
    frames = np.arange(n) if frames is None else np.asarray(frames)
    kids = [int(c) for c in np.flatnonzero(parent >= 0)]
    sets = [b for b in bundles(groups, parent, kids) if only is None or set(b.joints) & set(only)]
    in_sets = {c for b in sets for c in b.joints}
    wanted = set(kids if only is None else only) | in_sets
    # Each joint between two framed bodies is Kirk's fit (with a small penalty, FIXED_PENALTY); each joint
    # of a bundle starts the bundle from Kirk's fit with Kirk's own penalty: the bundle, with hardly any
    # penalty, leaves a hinge's point where it starts along the axis, and it had better start near the markers.
    kirk = tree_joint_points(markers, groups, parent, sorted(wanted - in_sets), frames, penalty=FIXED_PENALTY)
    start = tree_joint_points(markers, groups, parent, sorted(in_sets), frames)
    points, rms, res = {**kirk.points, **start.points}, {**kirk.rms, **start.rms}, {**kirk.residuals, **start.residuals}
    few = frames[np.linspace(0, len(frames) - 1, min(BUNDLE_FRAMES, len(frames))).astype(int)]
    for bundle in sets:
        placed = bundle_joint_points(markers, groups, bundle, {c: start.points[c][few] for c in bundle.joints}, few)
        for c, p in placed.items():
            M = markers[:, np.concatenate([groups[c], groups[int(parent[c])]])]
            d = np.linalg.norm(M - p[:, None], axis=-1)
            e = d - np.nanmedian(d, axis=0)
            points[c], res[c] = p, e
            rms[c] = float(np.sqrt(np.nanmean(e[frames] ** 2)))
    return points, rms, res


def marker_hinges(markers: np.ndarray, shapes, pairs: np.ndarray, rotations: np.ndarray, valid: np.ndarray):
    """For each tree joint (child, parent) in `pairs`: whether it is a hinge, and its axis in the child's and
    the parent's shape frame (NaN elsewhere): the two bodies' relative rotation beyond its noise
    (ROTATION_MARGIN in variance, as `articulation.judge` reads it) about one axis only. The noise is the
    relative rotation's own white part, read from its fourth differences over consecutive frames
    (`marker_noise`): with fixed markers the poses' noise is white and their motion smooth. A body of three
    markers or more is posed from its markers alone, one of fewer by `rotations` (its markers and joints)."""
    from flockcal.solver.optical.articulation import ROTATION_MARGIN
    from flockcal.solver.optical.marker_noise import FOURTH_DIFFERENCE_GAIN
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
        idx = np.flatnonzero(oka & okb)
        run = idx[4:] - idx[:-4] == 4  # five consecutive frames
        if run.sum() < 20:
            continue
        Q = Ra[idx].transpose(0, 2, 1) @ Rb[idx]  # the parent in the child's frame
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
            continue
        axis = V[:, 2]  # the rotation vectors' one direction: the axis, child's frame
        hinge[i], ax_c[i], ax_p[i] = True, axis, Qm.T @ axis
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
