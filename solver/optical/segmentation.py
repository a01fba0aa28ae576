"""Which markers ride on one rigid body, on real skin markers: two groups are two bodies when a joint
explains their relative motion, however small, and one body when their relative rotation stays within
what their own markers' soft tissue gives their poses, however large the skin's sliding.

Average linkage of every marker pair's distance range proposes the merges, closest first; each merge of
two groups with a pose of their own (three or more markers) is judged by `articulation.judge`:
- "skin" (rotation within the poses' noise) or "twist" (one segment turning about its length): one body,
  up to twice the soft-tissue tolerance of relative motion (two markers sliding the whole way apart);
- "joint" (a joint pins the centre, design.md §3a): two bodies, at any size;
- "moved" (turned beyond noise, no joint pinned) or unjudged (a group of one or two markers): the size
  decides, one body within the soft-tissue tolerance (`RIGID_TOLERANCE_M`).
Two markers the size would put with a framed group stay apart when a third framed group pins a joint to
them that the group does not turn about (`Judge.joint_elsewhere`). A second pass looks at each group from
the others' frames (small rotations a distance hardly shows) with the same verdicts, and each marker
finally goes to the body it is stillest in; two markers left alone are one body when a framed body pins a
joint to them as a unit (`pair_lone_markers`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from flockcal.errors import FlockcalError
from flockcal.solver.optical.articulation import (
    JOINT_TOLERANCE_M, UNJUDGED, GroupPose, Verdict, group_pose, judge, point_joint, point_joints, relative_motion,
)
from flockcal.solver.optical.linkage import canonical, linkage_labels, linkage_matrix
from flockcal.solver.optical.rigid import procrustes_mean, rigid_fit, to_body

# Skin markers slide over the bone by 5–15 mm at the ends of a joint's range (soft-tissue artefact), so two
# markers of one segment can change their distance by up to about this much. Relative motion within it,
# which no joint explains, is read as "did not move relative to each other"; beyond twice it (two markers
# sliding the whole way apart) it is never skin. A range is the 10th–90th percentile spread over the take
# (a label swap or glitch in under a tenth of the frames does not widen it).
RIGID_TOLERANCE_M = 0.015
SKIN_REACH = 2.0  # × the tolerance: relative motion soft tissue can make at most
LOW_Q, HIGH_Q = 0.10, 0.90

# Frames the segmentation reads: runs of consecutive frames spread over the take, so the poses' rotation
# jitter (third differences) and the batch-means blocks of the pair fits are those of real consecutive
# frames, while the runs cover every part of the motion. A run is one batch-means block. A verdict that
# decides a merge is read again on THOROUGH_RUNS runs (every frame of a take up to 1920 frames).
RUN_FRAMES = 64
RUNS = 10
THOROUGH_RUNS = 30
SEGMENT_FRAMES = 250

# A joint between a framed group and two markers the linkage is about to merge keeps them apart only when
# pinned within the sensor path's own tolerance (design.md §3a), not the 10 mm three-marker poses earn.
PAIR_JOINT_M = 0.005

# A body needs this many markers to have a frame of its own (three non-collinear points).
FRAMED = 3
LEAVE_OUT_BELOW = 8  # bodies this small judge their own markers with each left out of the fit


# Stands in for "no frame to see it from" inside sums (any real motion is far below a kilometre).
UNSEEN_M = 1e3


class SegmentationError(FlockcalError):
    """The markers could not be grouped into rigid bodies."""


@dataclass(frozen=True)
class Merge:
    """Two groups of markers made one body, and why (the verdict on them, and how far they moved apart)."""

    a: tuple[int, ...]
    b: tuple[int, ...]
    verdict: Verdict
    motion_m: float  # their relative motion: mean distance range, or mean motion in each other's frames
    seen_from_frames: bool  # judged in the second pass (motion in each other's frames)


@dataclass(frozen=True)
class Segmentation:
    labels: np.ndarray  # (k,) body index of every marker, bodies numbered by their first marker
    n_groups: int
    tolerance_m: float  # relative motion soft tissue makes: within it, no joint, one body
    distance_range: np.ndarray  # (k, k) 10–90 % range of every inter-marker distance (m); inf: never seen together
    internal_motion: np.ndarray  # (G,) mean distance range inside each body (m); 0 for a single marker
    frames: np.ndarray  # frames the distance ranges were read on
    parts: np.ndarray = field(default=None)  # (k,) rigid part of every marker: a body's parts moved against each other
    merges: tuple[Merge, ...] = ()  # merges of two groups of three or more markers, in the order made

    @property
    def groups(self) -> list[np.ndarray]:
        return [np.flatnonzero(self.labels == g) for g in range(self.n_groups)]

    def body_parts(self, g: int) -> list[np.ndarray]:
        """Body g's rigid parts (marker indices), largest first: groups that turned against each other
        beyond their poses' noise yet stayed within the soft-tissue tolerance, so were kept as one body."""
        idx = np.flatnonzero(self.labels == g)
        if self.parts is None:
            return [idx]
        out = [idx[self.parts[idx] == p] for p in np.unique(self.parts[idx])]
        return sorted(out, key=lambda x: (-len(x), int(x[0])))


def quantile_range(x: np.ndarray, axis: int = 0, low: float = LOW_Q, high: float = HIGH_Q, min_count: int = 5) -> np.ndarray:
    """high − low quantile of `x` along `axis`, NaN ignored; inf where fewer than `min_count` values.

    One sort for both quantiles (nanquantile sorts per call and is ~10× slower on (frames, k, k))."""
    s = np.sort(np.moveaxis(np.asarray(x, dtype=float), axis, 0), axis=0)  # NaN sort last
    cnt = np.isfinite(s).sum(0)
    last = np.maximum(cnt - 1, 0)
    lo = np.take_along_axis(s, np.round(low * last).astype(int)[None], 0)[0]
    hi = np.take_along_axis(s, np.round(high * last).astype(int)[None], 0)[0]
    return np.where(cnt >= min_count, hi - lo, np.inf)


def distance_ranges(markers: np.ndarray) -> np.ndarray:
    """(k, k) 10–90 % range of every inter-marker distance over the frames given; inf where two markers
    were seen together in too few frames to say; 0 on the diagonal."""
    d = np.linalg.norm(markers[:, :, None, :] - markers[:, None, :, :], axis=-1)
    out = quantile_range(d)
    np.fill_diagonal(out, 0.0)
    return out


def motion_in_frames(markers: np.ndarray, labels: np.ndarray, cache: dict | None = None) -> np.ndarray:
    """(k, G) how far each marker moves in each body's own frame (2 × the 90 % quantile of its distance
    from its median position there: comparable to a distance range); inf for bodies without a frame.
    `cache` keeps each body's column by its members, so a merge recomputes only the merged body."""
    k = markers.shape[1]
    G = int(labels.max()) + 1
    out = np.full((k, G), np.inf)
    cache = {} if cache is None else cache
    for g in range(G):
        members = np.flatnonzero(labels == g)
        key = tuple(members.tolist())
        if key not in cache:
            cache[key] = body_motion(markers, members)
        out[:, g] = cache[key]
    return out


def body_motion(markers: np.ndarray, members: np.ndarray) -> np.ndarray:
    """(k,) every marker's motion in the frame of the body made of `members` (inf: no frame).

    A member is left out of the fit that judges it while the body keeps three markers and is small
    enough for one marker to hold it still (a marker pulls a fit of q markers by about 1/q of its motion;
    at LEAVE_OUT_BELOW markers and more that is within the tolerance's rounding and not worth a refit)."""
    out = np.full(markers.shape[1], np.inf)
    if len(members) < FRAMED:
        return out
    shape, R, t, ok = procrustes_mean(markers[:, members])
    if ok.sum() < 10:
        return out
    out[:] = spread_in_frame(markers[ok], R[ok], t[ok])
    if FRAMED < len(members) < LEAVE_OUT_BELOW:
        for pos, i in enumerate(members):
            rest = np.delete(np.arange(len(members)), pos)
            Ri, ti, oki = rigid_fit(shape[rest], markers[:, members[rest]])
            if oki.sum() >= 10:
                out[i] = spread_in_frame(markers[oki][:, [i]], Ri[oki], ti[oki])[0]
    return out


def spread_in_frame(markers: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(q,) 2 × 90 % quantile of each marker's distance from its median position in the frame (R, t)."""
    y = to_body(R, t, markers)  # (f, q, 3)
    med = np.nanmedian(y, axis=0)
    dev = np.linalg.norm(y - med[None], axis=-1)
    s = np.sort(dev, axis=0)
    cnt = np.isfinite(s).sum(0)
    q = np.take_along_axis(s, np.round(HIGH_Q * np.maximum(cnt - 1, 0)).astype(int)[None], 0)[0]
    return np.where(cnt >= 5, 2.0 * q, np.inf)


class Judge:
    """Verdicts on pairs of marker groups, each pose and verdict computed once per membership.

    Poses and verdicts are read on the segmentation's runs of frames; a verdict of "moved" (turned, no
    joint pinned) that would let the size merge the two groups is read again on THOROUGH_RUNS runs
    (`thorough`): a joint exercised in one stretch of the take (one limb after another) is pinned by the
    blocks where it moved, which RUNS runs sample only a few of."""

    def __init__(self, markers: np.ndarray, frames: np.ndarray):
        thorough = judging_frames(len(markers), runs=THOROUGH_RUNS)
        self.markers = markers[frames]
        # A short take is read whole both ways: the thorough poses are the quick ones.
        self.same = len(thorough) == len(frames) and bool(np.array_equal(thorough, frames))
        self.all = self.markers if self.same else markers[thorough]
        self._poses: dict[tuple, GroupPose | None] = {}
        self._verdicts: dict[tuple, Verdict] = {}

    def pose(self, members, thorough: bool = False) -> GroupPose | None:
        key = (tuple(sorted(int(i) for i in members)), thorough and not self.same)
        if key not in self._poses:
            if key[1]:
                quick = self.pose(key[0])
                self._poses[key] = None if quick is None else group_pose(self.all, np.array(key[0]), shape=quick.shape)
            else:
                self._poses[key] = group_pose(self.markers, np.array(key[0]))
        return self._poses[key]

    def __call__(self, a, b, thorough: bool = False) -> Verdict:
        ka, kb = tuple(sorted(int(i) for i in a)), tuple(sorted(int(i) for i in b))
        key = ((ka, kb) if ka < kb else (kb, ka)) + (thorough and not self.same,)
        if key not in self._verdicts:
            self._verdicts[key] = judge(self.pose(key[0], thorough), self.pose(key[1], thorough))
        return self._verdicts[key]

    def small(self, framed, few, tolerance: float = JOINT_TOLERANCE_M) -> Verdict:
        """The verdict on a framed group and one or two markers (`articulation.point_joint`), read on
        every frame."""
        ka, kb = tuple(sorted(int(i) for i in framed)), tuple(sorted(int(i) for i in few))
        key = ("small", ka, kb, tolerance)
        if key not in self._verdicts:
            pose = self.pose(ka, thorough=True)
            self._verdicts[key] = (UNJUDGED if pose is None else
                                   point_joint(pose, self.all[:, np.array(kb)], tolerance=tolerance))
        return self._verdicts[key]

    def pair_joint(self, framed, pair):
        """The joint between the framed group `framed` and two markers `pair` when it is one a tree edge to
        two markers asks (`two_marker.determined`: a point fixed in `framed`'s frame at constant distances
        from both, "joint", pinned within PAIR_JOINT_M, their distances to it constant within
        JOINT_TOLERANCE_M rms), read on every frame: (verdict, centre in `framed`'s frame); else None."""
        key = ("pair_joint", tuple(sorted(int(i) for i in framed)), tuple(sorted(int(i) for i in pair)))
        if key not in self._verdicts:
            pose = self.pose(key[1], thorough=True)
            self._verdicts[key] = None
            if pose is not None:
                pj = point_joints(pose, self.all[:, list(key[2])][:, None], PAIR_JOINT_M)
                v = pj.verdicts[0]
                if v.kind == "joint" and v.joint_error_m <= PAIR_JOINT_M and pj.rms_m[0] <= JOINT_TOLERANCE_M:
                    self._verdicts[key] = (v, pj.centre[0])
        return self._verdicts[key]

    def joint_elsewhere(self, framed, pair, others) -> Verdict | None:
        """Two markers `pair` are not of the framed group `framed` when a third framed group h (among
        `others`) pins a joint to them (`pair_joint`) that `framed` does not turn about: `framed`'s markers
        (up to JUDGED_MARKERS, spread) keep their distances to that point of h's frame no better than
        JOINT_TOLERANCE_M rms, the pair's own bound. One rigid body turns about one point of a neighbour
        (issue 31: a trunk segment of two markers that the size put with the body beyond its neighbour).
        Returns the pair's joint verdict then, else None."""
        mine = set(int(i) for i in framed) | set(int(i) for i in pair)
        for h in others:
            if mine & set(int(i) for i in h):
                continue
            joint = self.pair_joint(h, pair)
            if joint is not None and self.radius_rms(h, framed, joint[1]) > JOINT_TOLERANCE_M:
                return joint[0]
        return None

    def radius_rms(self, framed, group, centre: np.ndarray) -> float:
        """Rms over up to JUDGED_MARKERS spread markers of `group` of their distance, in the frame of the
        framed group `framed`, to the point `centre` of that frame about its mean (every frame)."""
        from flockcal.solver.optical.two_marker import spread

        pose = self.pose(framed, thorough=True)
        pick = spread(self.all, np.asarray(sorted(int(i) for i in group)))
        y = to_body(np.where(pose.ok[:, None, None], pose.R, np.eye(3)), pose.t, self.all[:, pick])[pose.ok]
        d = np.linalg.norm(y - centre, axis=-1)
        dev = d - np.nanmean(d, axis=0)[None]
        return float(np.sqrt(np.nanmean(dev**2)))

    def decide(self, a, b, motion: float, tolerance: float, others=()) -> tuple[Verdict, bool]:
        """(verdict, whether a and b are one body by `joins`), read thoroughly where it matters. `others`:
        the framed groups that may pin a joint to two markers elsewhere (`joint_elsewhere`)."""
        framed, few = (a, b) if len(a) >= len(b) else (b, a)
        if len(few) < FRAMED:
            verdict = UNJUDGED
            if len(few) == 2 and len(framed) >= FRAMED and motion <= tolerance:
                # Two markers have a direction: a joint that pins a point between them and a framed group
                # keeps them apart (a pelvis of two markers must not go into the abdomen a joint moved it
                # against). Read at the sensor path's 5 mm (PAIR_JOINT_M): the pair is any two markers the
                # linkage put together so far, and skin sliding in step with a joint pins a pivot too (the
                # real knee trial's RTHI2+RTHI3 against the epicondyles and RTHI1: 8.9 mm). Read only
                # where the size alone would merge them: beyond the tolerance it refuses anyway.
                verdict = self.small(framed, few, PAIR_JOINT_M)
                if verdict.kind != "joint":
                    verdict = self.joint_elsewhere(framed, few, others) or verdict
            if motion <= tolerance and len(few) >= 2:
                # Two markers with no pose of their own join a group only if they stay within the tolerance
                # also where they moved most (5–95 %, not 10–90 %); a framed group's swaps left out. A lone
                # marker's own label swap would count there, so it goes by the 10–90 % range alone.
                pose = self.pose(framed, thorough=True) if len(framed) >= FRAMED else None
                big = pose.clean if pose is not None else self.all[:, np.asarray(framed, dtype=int)]
                motion = max(motion, relative_motion(big, self.all[:, np.asarray(few, dtype=int)]))
        else:
            verdict = self(a, b)
            if verdict.kind == "moved" and motion <= tolerance:
                # More frames shrink a standard error as 1/√frames: read again only a joint they could pin.
                gain = np.sqrt(len(self.all) / len(self.markers))
                thorough = not self.same and verdict.across_m <= 1.5 * gain * JOINT_TOLERANCE_M
                if thorough:
                    verdict = self(a, b, thorough=True)
                if verdict.kind == "moved":
                    # Groups that turned against each other are one body only if they also stayed within
                    # the tolerance when they moved most (in part of the take, the 10–90 % range hides it).
                    motion = max(motion, relative_motion(self.pose(a, thorough).clean, self.pose(b, thorough).clean))
        return verdict, joins(verdict, motion, tolerance)


def in_frame_motion(pose: GroupPose, points: np.ndarray, high: float = 0.98) -> float:
    """Mean over `points` (n, q, 3) of 2 × the `high` quantile of their distance from their median
    position in the frame of `pose` (comparable to a distance range)."""
    y = to_body(np.where(pose.ok[:, None, None], pose.R, np.eye(3)), pose.t, points)[pose.ok]
    dev = np.linalg.norm(y - np.nanmedian(y, axis=0)[None], axis=-1)
    s = np.sort(dev, axis=0)
    cnt = np.isfinite(s).sum(0)
    q = np.take_along_axis(s, np.round(high * np.maximum(cnt - 1, 0)).astype(int)[None], 0)[0]
    q = q[cnt >= 5]
    return float(2.0 * q.mean()) if q.size else float("inf")


def joins(verdict: Verdict, motion: float, tolerance: float) -> bool:
    """The rule: never one body across a joint, whatever the size; within the tolerance one body otherwise
    (skin, a twist, groups that turned with no joint pinned, or a group with no pose to judge); beyond it,
    up to SKIN_REACH × tolerance, only groups that turned against each other no more than their poses'
    noise predicts (rotation ratio ≤ 1): skin sliding far, with nothing turning."""
    if verdict.kind in ("skin", "twist"):
        within_noise = verdict.kind == "skin" and verdict.rotation_ratio <= 1.0
        return motion <= (SKIN_REACH if within_noise else 1.0) * tolerance
    if verdict.kind == "joint":
        return False
    return motion <= tolerance


class Grouping:
    """Bodies and their rigid parts while segmentation merges them, with the log of merges."""

    def __init__(self, k: int):
        self.labels = np.arange(k)
        self.parts = np.arange(k)
        self.merges: list[Merge] = []

    def members(self, g: int) -> np.ndarray:
        return np.flatnonzero(self.labels == g)

    def framed(self) -> list[np.ndarray]:
        """The members of every body with a frame of its own (FRAMED markers or more)."""
        return [m for m in (self.members(g) for g in np.unique(self.labels)) if len(m) >= FRAMED]

    def merge(self, a: int, b: int, verdict: Verdict, motion: float, ranges: np.ndarray, in_frames: bool) -> None:
        """Body b into body a. Skin, a twist or an unjudged small group joins the part of the other body
        nearest to it (one part each side: the parts become one); groups that turned beyond noise ("moved",
        or a forced count) keep their parts apart."""
        ia, ib = self.members(a), self.members(b)
        if len(ia) >= FRAMED and len(ib) >= FRAMED:
            self.merges.append(Merge(tuple(ia.tolist()), tuple(ib.tolist()), verdict, float(motion), in_frames))
        pa, pb = np.unique(self.parts[ia]), np.unique(self.parts[ib])
        if verdict.kind in ("skin", "twist", "unjudged") and (len(pa) == 1 or len(pb) == 1):
            single, many = (pb, ia) if len(pb) == 1 else (pa, ib)
            near = nearest_part(ranges, self.parts, np.flatnonzero(self.parts == single[0]), many)
            self.parts[self.parts == single[0]] = near
        self.labels[ib] = a


def nearest_part(ranges: np.ndarray, parts: np.ndarray, idx: np.ndarray, others: np.ndarray) -> int:
    """The part among `others`' markers with the smallest mean distance range to the markers `idx`."""
    best, best_range = int(parts[others[0]]), np.inf
    for p in np.unique(parts[others]):
        block = ranges[np.ix_(idx, others[parts[others] == p])]
        r = float(np.mean(np.where(np.isfinite(block), block, UNSEEN_M)))
        if r < best_range:
            best, best_range = int(p), r
    return best


def judged_linkage(ranges: np.ndarray, tolerance: float, judge_pair: Judge, grouping: Grouping) -> None:
    """Average linkage of the distance ranges, closest pair first, each merge allowed by `joins`; a pair
    it refuses is set aside and the next closest tried, until no pair within SKIN_REACH × tolerance is left."""
    k = len(ranges)
    D = linkage_matrix(ranges, tolerance)
    size = np.ones(k)
    refused = np.zeros((k, k), dtype=bool)
    reach = SKIN_REACH * tolerance
    while True:
        open_ = np.where(refused, np.inf, D)
        a, b = np.unravel_index(np.argmin(open_), D.shape)
        d = float(open_[a, b])
        if not d <= reach:
            return
        verdict, ok = judge_pair.decide(grouping.members(a), grouping.members(b), d, tolerance, grouping.framed())
        if not ok:
            refused[a, b] = refused[b, a] = True
            continue
        grouping.merge(a, b, verdict, d, ranges, in_frames=False)
        # The merged cluster's mean range to every other: the size-weighted mean of its two parts'.
        row = (size[a] * D[a] + size[b] * D[b]) / (size[a] + size[b])
        D[a], D[:, a] = row, row
        D[a, a] = np.inf
        D[b], D[:, b] = np.inf, np.inf
        refused[a], refused[:, a] = False, False
        size[a] += size[b]


def merge_still_bodies(markers: np.ndarray, grouping: Grouping, tolerance: float, judge_pair: Judge | None,
                       ranges: np.ndarray, n_groups: int | None = None) -> None:
    """Merge bodies that did not move relative to each other and move markers to the body they are still
    in, judged in the bodies' own frames (a rotation of a few degrees moves a marker a long way from the
    joint while hardly changing distances to markers near it); each merge is allowed by `joins`."""
    cache: dict = {}
    refused: set = set()
    for _ in range(len(grouping.labels)):
        labels = canonical(grouping.labels)
        ids = np.unique(grouping.labels)  # body g of `labels` is grouping's body ids[g]
        G = len(ids)
        if G == 1 or (n_groups is not None and G <= n_groups):
            break
        motion = motion_in_frames(markers, labels, cache)
        # Body B as seen from A: mean motion of B's markers in A's frame; the better-framed view decides.
        member = np.eye(G, dtype=bool)[labels]  # (k, G)
        capped = np.minimum(motion, UNSEEN_M)  # inf · 0 would be NaN in the product
        seen_from = (capped.T @ member) / np.maximum(member.sum(0), 1)[None]  # (A, B)
        seen_from[seen_from >= UNSEEN_M] = np.inf
        pair = np.minimum(seen_from, seen_from.T)
        np.fill_diagonal(pair, np.inf)
        merged = False
        for flat in np.argsort(pair, axis=None):
            a, b = np.unravel_index(flat, pair.shape)
            if a > b:
                continue
            d = float(pair[a, b])
            if n_groups is not None:
                verdict, ok = Verdict("unjudged", float("nan"), float("nan")), np.isfinite(d)
            else:
                if not d <= SKIN_REACH * tolerance:
                    break
                key = (tuple(np.flatnonzero(labels == a)), tuple(np.flatnonzero(labels == b)))
                if key in refused:
                    continue
                verdict, ok = judge_pair.decide(*key, d, tolerance, grouping.framed())
                if not ok:
                    refused.add(key)
            if ok:
                grouping.merge(int(ids[a]), int(ids[b]), verdict, d, ranges, in_frames=True)
                merged = True
                break
        if not merged:
            if n_groups is None:
                reassign(motion, labels, tolerance, grouping, ids, ranges)
            break


def reassign(motion: np.ndarray, labels: np.ndarray, tolerance: float, grouping: Grouping, ids: np.ndarray,
             ranges: np.ndarray) -> None:
    """Each marker to the framed body it moves least in, when it is still there (within `tolerance`) and
    stiller than in its own body; a body is never emptied below a frame by this. A marker near a joint
    (on its axis: an epicondyle, a malleolus) is still in both bodies' frames: it goes to the one it moves
    least in, into the part of that body nearest to it."""
    labels = labels.copy()
    best = np.argmin(motion, axis=1)
    gain = motion[np.arange(len(labels)), best]
    own = motion[np.arange(len(labels)), labels]
    for i in np.argsort(gain):
        g = best[i]
        if g == labels[i] or not gain[i] <= tolerance or not gain[i] < own[i]:
            continue
        size = np.sum(labels == labels[i])
        if size == FRAMED:  # leaving would cost the body its frame
            continue
        labels[i] = g
        target = np.flatnonzero((labels == g) & (np.arange(len(labels)) != i))
        grouping.parts[i] = nearest_part(ranges, grouping.parts, np.array([i]), target)
        grouping.labels[i] = ids[g]


def adopt_small_pieces(grouping: Grouping, tolerance: float, ranges: np.ndarray, judge_pair: Judge) -> None:
    """A body of one or two markers has no pose: no joint to it can be judged, and skin that slid one
    marker away from its segment's others (soft tissue of two joints on a shank) would leave it alone.
    A lone marker joins the framed body it moved least against (mean distance range) when that stays
    within the reach of soft tissue (SKIN_REACH × tolerance); a pair of markers, which has a direction,
    by `joins` on its verdict there (`articulation.point_joint`). Otherwise a small piece is a body of
    its own."""
    R = np.where(np.isfinite(ranges), ranges, UNSEEN_M)
    refused: set = set()
    while True:
        ids = np.unique(grouping.labels)
        members = [grouping.members(g) for g in ids]
        framed = [g for g, m in zip(ids, members) if len(m) >= FRAMED]
        best = None
        for g, m in zip(ids, members):
            if len(m) >= FRAMED:
                continue
            for h in framed:
                d = float(R[np.ix_(m, grouping.members(h))].mean())
                if d <= SKIN_REACH * tolerance and (best is None or d < best[0]) and (int(g), int(h)) not in refused:
                    best = (d, int(g), int(h))
        if best is None:
            return
        d, g, h = best
        if len(grouping.members(g)) == 2:
            verdict = judge_pair.small(grouping.members(h), grouping.members(g))
            if verdict.kind != "joint":
                verdict = judge_pair.joint_elsewhere(grouping.members(h), grouping.members(g), grouping.framed()) or verdict
            if not joins(verdict, d, tolerance):
                refused.add((g, h))
                continue
        grouping.merge(h, g, Verdict("unjudged", float("nan"), float("nan")), d, ranges, in_frames=False)


def pair_lone_markers(grouping: Grouping, tolerance: float, ranges: np.ndarray, judge_pair: Judge) -> None:
    """Two markers left alone (no framed body within the skin's reach adopted them) whose distance varies
    beyond the tolerance but within the skin's reach (SKIN_REACH × tolerance: one segment's two markers,
    each slid by a joint at either end) are one body when a framed body pins a joint to them as a unit
    (`Judge.pair_joint`: a point of its frame at constant distances from both). Markers of two segments
    with a joint between them do not both turn about one point of a third body. Closest pairs first
    (issue 31: the simulated walk seed 3's right upper arm, 15.1 mm of distance range, its shoulder pinned
    to 2.0 mm from the chest)."""
    ids = np.unique(grouping.labels)
    lone = [int(grouping.members(g)[0]) for g in ids if len(grouping.members(g)) == 1]
    pairs = sorted((float(ranges[i, j]), i, j) for n, i in enumerate(lone) for j in lone[n + 1:]
                   if ranges[i, j] <= SKIN_REACH * tolerance)
    used: set = set()
    for d, i, j in pairs:
        if used & {i, j}:
            continue
        if any(judge_pair.pair_joint(f, [i, j]) is not None for f in grouping.framed()):
            # One part: the two are one segment's markers, like a small piece adopted by a body.
            grouping.merge(int(grouping.labels[i]), int(grouping.labels[j]), UNJUDGED, d, ranges, in_frames=False)
            used |= {i, j}


def judging_frames(n: int, runs: int = RUNS, run: int = RUN_FRAMES) -> np.ndarray:
    """Runs of `run` consecutive frames spread evenly over n frames (all frames when they are fewer)."""
    if n <= runs * run:
        return np.arange(n)
    starts = np.linspace(0, n - run, runs).round().astype(int)
    return (starts[:, None] + np.arange(run)[None]).ravel()


def segment_markers(
    markers: np.ndarray,
    tolerance: float = RIGID_TOLERANCE_M,
    n_groups: int | None = None,
) -> Segmentation:
    """Group the k markers of a take (n, k, 3, NaN gaps) into rigid bodies (module docstring: two bodies
    when a joint explains their relative motion, one when it is soft tissue); `tolerance` is the relative
    motion (metres, 10–90 % range) soft tissue makes, `n_groups` forces the count."""
    markers = np.asarray(markers, dtype=float)
    if markers.ndim != 3 or markers.shape[2] != 3:
        raise SegmentationError(f"markers must have shape (frames, markers, 3), got {markers.shape}")
    n, k, _ = markers.shape
    if k < 2:
        raise SegmentationError(f"need at least two markers to find rigid bodies, got {k}")
    if not tolerance > 0:
        raise SegmentationError(f"the rigid tolerance must be positive, got {tolerance!r} m")
    frames = judging_frames(n)
    # Distances and motion in the bodies' frames on SEGMENT_FRAMES of them: relative motion is slow next to
    # 100 Hz, and more frames change a range by well under a millimetre at a cost of frames × markers².
    few = frames[np.unique(np.linspace(0, len(frames) - 1, min(len(frames), SEGMENT_FRAMES)).round().astype(int))]
    M = markers[few]
    ranges = distance_ranges(M)
    grouping = Grouping(k)
    judge_pair = Judge(markers, frames)
    if n_groups is None:
        judged_linkage(ranges, tolerance, judge_pair, grouping)
    else:
        grouping.labels = linkage_labels(ranges, tolerance, n_groups)
    merge_still_bodies(M, grouping, tolerance, judge_pair, ranges, n_groups)
    if n_groups is None:
        adopt_small_pieces(grouping, tolerance, ranges, judge_pair)
        pair_lone_markers(grouping, tolerance, ranges, judge_pair)
    labels = canonical(grouping.labels)
    G = int(labels.max()) + 1
    internal = np.zeros(G)
    for g in range(G):
        idx = np.flatnonzero(labels == g)
        if len(idx) > 1:
            block = ranges[np.ix_(idx, idx)][~np.eye(len(idx), dtype=bool)]
            block = block[np.isfinite(block)]
            internal[g] = float(block.mean()) if block.size else np.nan
    return Segmentation(labels, G, float(tolerance), ranges, internal, few, canonical(grouping.parts),
                        tuple(grouping.merges))
