"""Bodies of two markers, whose pose is free about the line between them: a joint to one is judged and
placed by the point fixed in a posed neighbour's frame at constant distances from both markers
(`articulation.point_joints`), and the joint lends the body the third point its pose lacks, so that two
such bodies can judge each other the same way.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from flockcal.solver.fits import TOLERANCE_M as SENSOR_TOLERANCE_M
from flockcal.solver.optical.articulation import JOINT_TOLERANCE_M, GroupPose, Verdict, group_pose, point_joints
from flockcal.solver.optical.rigid import apply, rigid_fit

PAIR = 2  # markers of a body judged here
PINNED_M = SENSOR_TOLERANCE_M  # a tree joint to a body of two markers: its centre pinned this well


@dataclass(frozen=True)
class PointJoint:
    """The joint between `framed` (a body with a pose: its own, or lent) and `pair` (a body of two markers,
    or of more: then both have a pose, and this is the direction with the smaller residual)."""

    framed: int
    pair: int
    verdict: Verdict
    centre: np.ndarray  # (3,) in `framed`'s pose frame
    rms_m: float  # the pair's markers' distance from the centre, rms about their constant radii
    axis: np.ndarray  # (3,) its least-pinned direction in `framed`'s frame (a hinge's axis)


@dataclass
class TwoMarkerJoints:
    """Point joints of every pair of bodies where one has two markers and the other a pose (its own or lent
    by its best joint), by the pair; `lent[b]`: the joint whose centre, with body b's two markers, gives b
    its pose (its best "joint" verdict: pinned within the 10 mm a pose earns, for judging only, not yet an
    edge)."""

    joints: dict[frozenset, PointJoint] = field(default_factory=dict)
    lent: dict[int, PointJoint] = field(default_factory=dict)
    poses: dict[int, GroupPose] = field(default_factory=dict)  # on the judging frames

    def rms(self, G: int) -> np.ndarray:
        """(G, G) the point joints' residuals (NaN where none was judged)."""
        out = np.full((G, G), np.nan)
        for j in self.joints.values():
            out[j.framed, j.pair] = out[j.pair, j.framed] = j.rms_m
        return out

    def candidate(self, G: int) -> np.ndarray:
        """(G, G) pairs whose joint the take determined: turned beyond noise, centre between them and pinned
        within the sensor path's own tolerance (PINNED_M), not the 10 mm a posed pair earns: two markers
        are any two the segmentation left together, and skin sliding in step with a joint pins a pivot too
        (the upper-limb file's two clavicle markers against the box: 7.8 mm). Only those may be a tree edge,
        as for two posed bodies (design.md §3a)."""
        out = np.zeros((G, G), dtype=bool)
        for j in self.joints.values():
            out[j.framed, j.pair] = out[j.pair, j.framed] = determined(j)
        return out


def determined(j: PointJoint) -> bool:
    """A point joint the take determined: turned beyond noise, its centre between the two bodies and pinned
    within PINNED_M, and the markers' distances to it constant within what skin leaves (JOINT_TOLERANCE_M
    rms: a larger residual is no joint, however well a least-squares point is pinned; the simulated walk's
    right forearm against the chest: 17 mm)."""
    return j.verdict.kind == "joint" and j.verdict.joint_error_m <= PINNED_M and j.rms_m <= JOINT_TOLERANCE_M


def lend(pose: GroupPose, pair: np.ndarray, centre: np.ndarray) -> GroupPose | None:
    """The pose of a body of two markers `pair` (n, 2, 3) from them and a joint at `centre` in `pose`'s frame."""
    p = apply(np.where(pose.ok[:, None, None], pose.R, np.eye(3)), pose.t, centre[None])  # (n, 1, 3)
    p[~pose.ok] = np.nan
    return group_pose(np.concatenate([pair, p], axis=1), np.arange(3))


# A body's markers a point joint is judged on at most: four spread ones pin a point as well as all of a
# thorax's thirteen (constant distances to three non-collinear markers already fix it in their frame), at
# a third of the cost.
JUDGED_MARKERS = 4


def spread(markers: np.ndarray, idx: np.ndarray, count: int = JUDGED_MARKERS) -> np.ndarray:
    """Up to `count` of the markers `idx`, spread out: greedily the farthest from those chosen (median
    distances over the frames), starting from the pair farthest apart."""
    if len(idx) <= count:
        return idx
    few = markers[:: max(1, len(markers) // 100), idx]  # a hundred frames give the distances to a millimetre
    d = np.nanmedian(np.linalg.norm(few[:, :, None] - few[:, None, :], axis=-1), axis=0)
    d = np.where(np.isfinite(d), d, 0.0)
    a, b = np.unravel_index(np.argmax(d), d.shape)
    chosen = [int(a), int(b)]
    while len(chosen) < count:
        chosen.append(int(np.argmax(d[chosen].min(0))))
    return idx[np.sort(chosen)]


def padded(markers: np.ndarray, picks: list[np.ndarray]) -> np.ndarray:
    """(n, S, q, 3) the markers `picks` of S bodies, each padded with unseen markers to q, the most any has."""
    q = max(len(p) for p in picks)
    M = np.concatenate([markers, np.full((len(markers), 1, 3), np.nan)], axis=1)
    gap = markers.shape[1]
    return np.stack([M[:, np.concatenate([p, np.full(q - len(p), gap)]).astype(int)] for p in picks], axis=1)


def judge_two_marker(markers: np.ndarray, groups: list[np.ndarray], poses: dict[int, GroupPose],
                     posed_pairs: np.ndarray | None = None) -> TwoMarkerJoints:
    """Point joints over the judging frames `markers` (n, k, 3): every posed body against every other body
    of two markers or more (a pair of posed bodies keeps the direction with the smaller residual), so that
    all their residuals are of one kind; then each body of two markers with a joint ("joint" verdict) to a
    posed one borrows the best such joint (least residual) as its third point, and is judged against the
    other bodies of two markers with that pose; repeated while new poses are lent (a chain of two-marker
    bodies from the trunk out). `posed_pairs` (G, G): the pairs of posed bodies to judge so (default all;
    a pair the pair fit left undetermined is no tree edge whatever its cost)."""
    out = TwoMarkerJoints(poses=dict(poses))
    pairs = [g for g in range(len(groups)) if len(groups[g]) == PAIR]
    if not pairs:
        return out
    framers = [g for g in poses if poses[g] is not None]
    targets = [g for g in range(len(groups)) if len(groups[g]) >= PAIR]
    picks = {b: spread(markers, groups[b]) for b in targets}
    done: set[int] = set()
    while True:
        for a in framers:
            if a in done:
                continue
            done.add(a)
            lent = a in out.lent
            others = [b for b in (pairs if lent else targets) if b != a
                      and not (lent and frozenset((a, b)) in out.joints)
                      and (len(groups[b]) == PAIR or posed_pairs is None or posed_pairs[a, b])]
            if not others:
                continue
            pj = point_joints(out.poses[a], padded(markers, [picks[b] for b in others]))
            for s, b in enumerate(others):
                key = frozenset((a, b))
                if np.isfinite(pj.rms_m[s]) and (key not in out.joints or pj.rms_m[s] < out.joints[key].rms_m):
                    out.joints[key] = PointJoint(a, b, pj.verdicts[s], pj.centre[s], float(pj.rms_m[s]), pj.axis[s])
        fresh = []
        for b in pairs:
            if b in out.lent:
                continue
            best = min((j for j in out.joints.values() if j.pair == b and j.verdict.kind == "joint"),
                       key=lambda j: j.rms_m, default=None)
            if best is None:
                continue
            pose = lend(out.poses[best.framed], markers[:, groups[b]], best.centre)
            if pose is not None:
                out.lent[b], out.poses[b] = best, pose
                fresh.append(b)
        if not fresh:
            return out
        framers = fresh


def full_pose(markers: np.ndarray, groups: list[np.ndarray], two: TwoMarkerJoints, g: int,
              cache: dict | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(R, t, ok) of body g on every frame of `markers`, in the frame its judging pose was read in: its own
    markers, or (a lent pose) its two markers and its lender's joint."""
    cache = {} if cache is None else cache
    if g not in cache:
        pose = two.poses[g]
        if g in two.lent:
            j = two.lent[g]
            R, t, ok = full_pose(markers, groups, two, j.framed, cache)
            p = apply(np.where(ok[:, None, None], R, np.eye(3)), t, j.centre[None])
            p[~ok] = np.nan
            pts = np.concatenate([markers[:, groups[g]], p], axis=1)
        else:
            pts = markers[:, groups[g]]
        full = group_pose(pts, np.arange(pts.shape[1]), shape=pose.shape)
        cache[g] = (full.R, full.t, full.ok) if full is not None else rigid_fit(pose.shape, pts)
    return cache[g]


def point_joint_centres(markers: np.ndarray, groups: list[np.ndarray], two: TwoMarkerJoints, parent: np.ndarray,
                        joints, placed: dict[int, np.ndarray]) -> tuple[dict[int, np.ndarray], dict[int, float]]:
    """({child: (n, 3) world joint centre per frame}, {child: residual rms (m)}) for the tree joints `joints`
    (children) that are point joints: the centre fixed in the framed side's pose (one point for the take,
    as the pair fit places a joint between two posed bodies), NaN where that pose is unknown. A hinge's
    point on its axis follows design.md §3c's first rule where it can: the foot of the perpendicular from
    the framed body's other joint (`placed`: world centres per frame of joints already placed, by child)."""
    cache: dict = {}
    points, rms = {}, {}
    for c in joints:
        j = two.joints[frozenset((int(c), int(parent[c])))]
        R, t, ok = full_pose(markers, groups, two, j.framed, cache)
        Rv = np.where(ok[:, None, None], R, np.eye(3))
        centre = j.centre
        if j.verdict.hinge:
            feet = []
            for other in (k for k in placed if k != int(c) and j.framed in (k, int(parent[k]))):
                y = np.einsum("nji,nj->ni", Rv, placed[other] - t)[ok]  # its centre in the framed body's frame
                s = np.nanmedian(y, axis=0)
                if np.isfinite(s).all():
                    feet.append(centre + j.axis * float(j.axis @ (s - centre)))
            if feet:
                centre = np.mean(feet, axis=0)
        p = apply(Rv, t, centre[None])[:, 0]
        p[~ok] = np.nan
        points[int(c)], rms[int(c)] = p, j.rms_m
    return points, rms
