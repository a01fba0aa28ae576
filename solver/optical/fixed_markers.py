"""The route for markers fixed on their bones (every body keeps its marker distances within the markers'
noise: `marker_noise`): the tree from Kirk's residual of every pair of bodies, every joint from the bundle of
the poses and offsets around it (`joint_bundle`); each hinge's point on its axis afterwards by design.md
§3c's rule (`fixed_hinges`).

With no skin, Kirk's distances are the sharpest test of a pair: a pose read from three markers close together
turns with their noise, and a joint placed through it moves by that turn times the lever (7 mm of scatter at
a hip from a thigh's three markers under 1 mm of noise), while a distance carries the noise once. To place
the joint, though, Kirk's free point in every frame forgets that each body's markers keep their shape; the
bundle poses each body in every frame against its markers and the joint together (the markers' own
likelihood), and pins a joint the take turned mostly about one axis (a walk's hip) about twice as sharply
along that axis: on a simulated walk's hips, within 1.5 mm over four draws of the noise where Kirk's point
came up to 3.6 mm off."""

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
    fitted together with one of them; default all): the bundle's (`joint_bundle.bundles`), started from
    Kirk's fit of all joints at once on `frames` (default all frames), which stands where a bundle finds too
    few frames to adjust on. Marker-frames off their body's shape beyond the noise (swapped labels,
    glitches) are left out (`blank_off_shape`)."""
    n = len(markers)
    markers = blank_off_shape(markers, groups, noise.sigma_m)
    frames = np.arange(n) if frames is None else np.asarray(frames)
    kids = [int(c) for c in np.flatnonzero(parent >= 0)]
    sets = [b for b in bundles(groups, parent, kids) if only is None or set(b.joints) & set(only)]
    wanted = sorted({c for b in sets for c in b.joints})
    # The bundle starts from Kirk's fit with Kirk's own penalty: with hardly any penalty of its own it leaves
    # a hinge's point where it starts along the axis, and it had better start near the markers.
    start = tree_joint_points(markers, groups, parent, wanted, frames)
    points, rms, res = dict(start.points), dict(start.rms), dict(start.residuals)
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

