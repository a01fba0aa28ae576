"""The optical pipeline end to end (Kirk, O'Brien & Forsyth 2005): markers → rigid groups → tree of
joints → joint trajectories → fixed skeleton → per-body poses, and the `fit-markers` JSON.

Marker swaps and glitches are caught as markers far from their body's fitted pose (they also show as a
jump of the joint centre); those marker-frames are blanked and the joints refitted once.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from flockcal.errors import FlockcalError
from flockcal.solver.calibration import Calibration
from flockcal.solver.fits import TOLERANCE_M as SENSOR_TOLERANCE_M
from flockcal.solver.optical.exercised import (
    Exercised, candidate_costs, exercise_report, joint_decision, judge_pairs, spanning_forest,
)  # fmt: skip
from flockcal.solver.optical.fixed_hinges import hinge_slides
from flockcal.solver.optical.fixed_markers import fixed_costs, fixed_joint_points, fixed_segmentation
from flockcal.solver.optical.joints import Tree, joint_point
from flockcal.solver.optical.marker_noise import MarkerNoise, marker_noise
from flockcal.solver.optical.pair_joints import pair_joint_points
from flockcal.solver.optical.projection import BodyShape, bone_lengths, skeleton_shapes
from flockcal.solver.optical.rotations import Outliers, body_poses, find_outliers, rigid_route_joint, robust_marker_residuals
from flockcal.solver.optical.segmentation import RIGID_TOLERANCE_M, Segmentation, segment_markers
from flockcal.solver.optical.two_marker import TwoMarkerJoints, judge_two_marker, point_joint_centres


class OpticalError(FlockcalError):
    """The markers do not support a skeleton fit (too few markers, frames or bodies)."""


@dataclass
class OpticalFit:
    marker_names: tuple[str, ...]
    labels: tuple[str, ...]  # body labels
    groups: list[np.ndarray]  # marker indices per body
    clustering: Segmentation
    tree: Tree
    shapes: list[BodyShape]
    bones: list[tuple[int, int | None, int, float]]
    joint_points: dict[int, np.ndarray]  # child group → (n, 3) world joint centre per frame
    joint_rms: dict[int, float]  # Kirk residual rms per tree joint (m)
    rotations: np.ndarray  # (n, m, 3, 3) body → world
    positions: np.ndarray  # (n, m, 3) body origin (its markers' centroid)
    valid: np.ndarray  # (n, m)
    outliers: Outliers
    rate_hz: float
    times: np.ndarray
    unused_markers: list[str] = field(default_factory=list)
    exercised: Exercised | None = None  # pair decisions over the bodies' marker-only poses
    joint_markers: dict[int, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)  # child → (its, parent's) markers the joint was fitted on
    pair_route: frozenset = frozenset()  # children of the joints placed by the pair fit over marker-only poses
    point_route: frozenset = frozenset()  # children of the joints to a body of two markers placed by `two_marker`
    noise: MarkerNoise | None = None  # the markers' noise, and whether they sit fixed on their bodies

    @property
    def parent(self) -> np.ndarray:
        return self.tree.parent

    def bodies(self) -> dict[str, list[str]]:
        return {lab: [self.marker_names[i] for i in g] for lab, g in zip(self.labels, self.groups)}

    def take(self):
        """The derived poses as a flockcal Take (docs/design.md §5), for `fit`, the exports and slippage."""
        from flockcal.takes import make_take

        return make_take(self.rotations, self.positions, self.labels, self.rate_hz, valid=self.valid, times=self.times)

    def calibration(self):
        """The fit as the solver's `Calibration` (see `fit_calibration`)."""
        return fit_calibration(self)

    def to_dict(self) -> dict:
        """`flockcal fit --json` shape (docs/design.md §5) plus "bodies", "markers" and "swap_events"."""
        return fit_json(self)


def body_labels(marker_names, groups) -> tuple[str, ...]:
    """A body is named after its markers' common prefix when it is a word of ≥ 2 characters
    ("LTHI", "LKNE" → no; "lthigh_1", "lthigh_2" → "lthigh"), else "body<k>"; labels stay unique."""
    labels = []
    for k, g in enumerate(groups):
        names = [marker_names[i] for i in g]
        prefix = os.path.commonprefix(names).rstrip("_-. :") if len(names) > 1 else ""
        lab = prefix if len(prefix) >= 2 else f"body{k}"
        labels.append(lab)
    for k, lab in enumerate(labels):
        if labels.count(lab) > 1:
            labels[k] = f"{lab}_{k}"
    return tuple(labels)


def topology_frames(visible: np.ndarray, count: int) -> np.ndarray:
    """`count` frames spread over the take, each the best-covered frame of its stretch."""
    n = len(visible)
    if n <= count:
        return np.arange(n)
    edges = np.linspace(0, n, count + 1).astype(int)
    seen = visible.sum(1)
    return np.array([s + int(np.argmax(seen[s:e])) for s, e in zip(edges[:-1], edges[1:]) if e > s])


def add_rigid_route_joints(shapes, weak, parent, R, t, valid, jp):
    """Offsets of the weak joints from the bodies' poses (rigid-transform route) added to both bodies'
    shapes; their per-frame points become the child's pose applied to c."""
    shapes = list(shapes)
    jp = dict(jp)
    for c in sorted(weak):
        p = int(parent[c])
        ok = valid[:, c] & valid[:, p]
        if ok.sum() < 10:
            continue
        cc, ll = rigid_route_joint(R[:, c], t[:, c], R[:, p], t[:, p], ok)
        for body, off in ((c, cc), (p, ll)):
            s = shapes[body]
            shapes[body] = replace(s, joints=s.joints + [c], joint_offsets=np.vstack([s.joint_offsets, off]))
        pts = np.einsum("nij,j->ni", R[:, c], cc) + t[:, c]
        pts[~ok] = np.nan
        jp[c] = pts
    return shapes, jp


def fit_joints(markers, groups, parent, frames=None, penalty: float = 1e-5, joint_groups=None, only=None):
    """Kirk fit of every tree joint on all (or the given, then extended to all) frames. Returns (points,
    rms, suspects): suspects (n, k) marks, in frames where a joint's residual jumps, the marker furthest
    from its constant distance (a swap shows up this way as a discontinuity of the joint centre).
    `joint_groups(child, parent)`: the markers of each side the joint is fitted on (default the bodies);
    `only`: the joints (by child) to fit, default all.

    The penalty stays (small): at a hinge every point of the axis keeps constant distances, and the
    penalty picks the one nearest the markers instead of letting it drift along the axis."""
    n, k, _ = markers.shape
    pick = joint_groups or (lambda a, b: (groups[a], groups[b]))
    joint_points, joint_rms = {}, {}
    suspects = np.zeros((n, k), dtype=bool)
    for child in np.flatnonzero(parent >= 0):
        if only is not None and int(child) not in only:
            continue
        gc, gp = pick(int(child), int(parent[child]))
        idx = np.concatenate([gc, gp])
        fit = joint_point(markers[:, gc], markers[:, gp], penalty=penalty, frames=frames, extend=True)
        joint_points[int(child)] = fit.points
        joint_rms[int(child)] = fit.rms
        mark_suspects(suspects, fit.residuals, idx)
    return joint_points, joint_rms, suspects


def mark_suspects(suspects: np.ndarray, residuals: np.ndarray, idx: np.ndarray) -> None:
    """In the frames where a joint's residual jumps (beyond 8 robust sd, and 1 cm), mark in `suspects` (n, k)
    the marker furthest from its constant distance; `residuals` (n, q) are those of the markers `idx`."""
    res = np.abs(residuals)
    fin = res[np.isfinite(res)]
    if fin.size:
        thr = max(8 * 1.4826 * np.median(fin), 0.01)
        worst = np.nanmax(np.nan_to_num(res, nan=0.0), axis=1)
        bad = np.flatnonzero(worst > thr)
        suspects[bad, idx[np.argmax(np.nan_to_num(res[bad], nan=0.0), axis=1)]] = True


def fixed_joints(markers, groups, parent, frames, noise, only=None):
    """`fit_joints` for markers fixed on their bones (`fixed_markers.fixed_joint_points`)."""
    points, rms, residuals = fixed_joint_points(markers, groups, parent, frames, noise, only)
    suspects = np.zeros(markers.shape[:2], dtype=bool)
    for c, res in residuals.items():
        mark_suspects(suspects, res, np.concatenate([groups[c], groups[int(parent[c])]]))
    return points, rms, suspects


# A refit without a few glitching marker-frames is skipped when it could move no body's fit by more than
# this: the glitches' summed residual over the body's seen marker-frames bounds the shift of its mean.
REFIT_SHIFT_M = 1e-4


def glitch_shift(residuals: np.ndarray, mask: np.ndarray, groups) -> float:
    """Largest, over bodies, of Σ masked marker-frames' residual / the body's seen marker-frames (m): how
    far leaving them out could move a whole-take mean of that body (inf when a residual is unknown)."""
    worst = 0.0
    for g in groups:
        bad = mask[:, g]
        if not bad.any():
            continue
        r = residuals[:, g][bad]
        if not np.isfinite(r).all():
            return float("inf")
        worst = max(worst, float(r.sum()) / max(int(np.isfinite(residuals[:, g]).sum()), 1))
    return worst


# Frames the joint fits are solved on at most (evenly thinned); the other frames get their joint points from
# the fitted radii. 1000 frames leave a joint's radii within a fraction of a millimetre of the all-frame fit
# on the simulated takes, at a third of the cost of a 30 s take at 144 Hz.
FIT_FRAMES = 1000


def joint_groups_of(segmentation: Segmentation, groups: list[np.ndarray]):
    """`joint_groups(a, b)`: the markers of body a and of body b a joint between them is fitted on. A body
    that absorbed several segments (rigid parts that turned against each other within the soft-tissue
    tolerance) is fitted on its part next to the other body (the smallest mean distance range to it), if
    that part has a pose of its own; otherwise on all its markers."""
    R = np.where(np.isfinite(segmentation.distance_range), segmentation.distance_range, 1e3)
    parts = [[p for p in segmentation.body_parts(g) if len(p) >= 3] for g in range(len(groups))]
    cache: dict = {}

    def side(a: int, b: int) -> np.ndarray:
        if (a, b) not in cache:
            if len(segmentation.body_parts(a)) == 1 or not parts[a]:
                cache[a, b] = groups[a]
            else:
                cache[a, b] = min(parts[a], key=lambda p: float(R[np.ix_(p, groups[b])].mean()))
        return cache[a, b]

    return lambda a, b: (side(a, b), side(b, a))


# A joint is placed by the pair fit over the marker-only poses when those pin its centre within the sensor
# path's own tolerance (design.md §3a, 5 mm) along every direction a joint pins (a hinge: across its axis).
# Beyond it a pose is too noisy at the joint (three markers close together on a pelvis: 16 mm of residual at
# the hip with 1 mm of noise) and Kirk's per-frame point, which needs no pose, does better.
PAIR_ROUTE_M = SENSOR_TOLERANCE_M


def pair_route(exercised: Exercised, child: int, parent: int) -> bool:
    """Whether the tree joint child–parent is placed by the pair fit over the bodies' poses (PAIR_ROUTE_M)."""
    if not exercised.judged[child, parent] or not exercised.determined[child, parent]:
        return False
    err = exercised.direction_error[child, parent]
    pinned = err[1:] if exercised.hinge[child, parent] else err
    return bool((pinned <= PAIR_ROUTE_M).all())


def two_marker_joints(markers: np.ndarray, groups: list[np.ndarray], shapes: dict | None = None,
                      posed_pairs: np.ndarray | None = None) -> TwoMarkerJoints:
    """The point joints of the bodies of two markers (`two_marker`), read on the segmentation's thorough
    frames with each posed body's pose there (from its whole-take shape in `shapes` where given); of the
    pairs of posed bodies, those in `posed_pairs` (default all)."""
    from flockcal.solver.optical.articulation import group_pose
    from flockcal.solver.optical.segmentation import THOROUGH_RUNS, judging_frames

    if not any(len(g) == 2 for g in groups):
        return TwoMarkerJoints()
    M = markers[judging_frames(len(markers), runs=THOROUGH_RUNS)]
    shapes = shapes or {}
    poses = {g: group_pose(M, idx, shape=shapes.get(g)) for g, idx in enumerate(groups) if len(idx) >= 3}
    return judge_two_marker(M, groups, poses, posed_pairs)


STAGES = ("segmentation", "exercised joints and tree", "joints and poses", "second pass without swaps")


def fit_markers(
    markers: np.ndarray,
    marker_names,
    rate_hz: float,
    times: np.ndarray | None = None,
    n_groups: int | None = None,
    root: int | str | None = None,
    topology_frame_count: int = 120,
    max_frames: int | None = FIT_FRAMES,
    min_seen: float = 0.2,
    rigid_tolerance: float = RIGID_TOLERANCE_M,
    progress: Callable[[str], None] | None = None,
) -> OpticalFit:
    """Skeleton from an (n, k, 3) marker take. Markers seen in under `min_seen` of the frames are left
    out (listed in `unused_markers`); takes longer than `max_frames` are thinned evenly for the joint
    fits (the poses are still produced for every frame). Markers whose relative motion stays within
    `rigid_tolerance` (m, 10–90 % range) are one body; only joints the take determines are tree edges
    (design.md §3a), so bodies no exercised joint reaches hang from nothing. `progress(stage)` is told each of STAGES as
    it begins (for a progress bar)."""
    step = progress or (lambda stage: None)
    markers = np.asarray(markers, dtype=float)
    names = tuple(str(x) for x in marker_names)
    n, k, _ = markers.shape
    times = np.arange(n) / rate_hz if times is None else np.asarray(times, dtype=float)
    seen = np.isfinite(markers).all(-1)
    keep = np.flatnonzero(seen.mean(0) >= min_seen)
    unused = [names[i] for i in range(k) if i not in set(keep.tolist())]
    if len(keep) < 2:
        raise OpticalError(f"only {len(keep)} marker(s) are seen in at least {min_seen:.0%} of the frames; need two or more")
    M = markers[:, keep]
    kept_names = tuple(names[i] for i in keep)

    step(STAGES[0])
    # Markers fixed on their bones group by their distances' noise (`fixed_markers`), else by articulation.
    clus = (fixed_segmentation(M, rigid_tolerance) if n_groups is None else None) or \
        segment_markers(M, tolerance=rigid_tolerance, n_groups=n_groups)
    groups = clus.groups
    if len(groups) < 2:
        raise OpticalError("all markers move as one rigid body: there is no joint to find (move the limbs)")
    labels = body_labels(kept_names, groups)
    if isinstance(root, str):
        if root not in labels:
            raise OpticalError(f"no body labelled {root!r}; the bodies are {', '.join(labels)}")
        root = labels.index(root)

    fit_frames = None if max_frames is None or n <= max_frames else np.linspace(0, n - 1, max_frames).astype(int)
    step(STAGES[1])
    topo = topology_frames(np.isfinite(M).all(-1), topology_frame_count)
    pick = joint_groups_of(clus, groups)
    exercised = judge_pairs(M, groups, joint_groups=pick)
    sizes = np.array([len(g) for g in groups])
    noise = marker_noise(M, groups)
    if noise.rigid:  # markers fixed on their bones: Kirk's distances judge every pair (`fixed_markers`)
        two = TwoMarkerJoints()
        tree = spanning_forest(fixed_costs(M, groups, noise, topo), sizes, root=root)
    else:
        # A body of two markers has no pose, but a joint to it has a centre fixed in its posed neighbour's
        # frame: judged so (`two_marker`), it needs no Kirk fit, which fits almost any pair under skin.
        two = two_marker_joints(M, groups, exercised.shapes, exercised.candidate())
        point_rms = two.rms(len(groups))
        posed_pair = exercised.judged & np.isfinite(exercised.rms)
        candidate = np.where(np.isfinite(point_rms) & ~posed_pair, two.candidate(len(groups)), exercised.candidate())
        tree = spanning_forest(candidate_costs(M, groups, topo, candidate, joint_groups=pick, exercised=exercised,
                                              points=point_rms), sizes, root=root)

    work = M.copy()
    outliers = None
    par = tree.parent
    # A joint between two bodies of one or two markers each is poorly pinned by the Kirk fit (four
    # distances for three unknowns a frame); such "weak" joints do not steer the poses and are solved
    # afterwards by the rigid-transform route from the poses the other joints and markers give.
    pointed = {int(c) for c in np.flatnonzero(par >= 0)
               if frozenset((int(c), int(par[c]))) in two.joints and min(sizes[c], sizes[par[c]]) < 3}
    weak = {int(c) for c in np.flatnonzero(par >= 0)
            if sizes[c] < 3 and sizes[par[c]] < 3 and c not in pointed and not noise.rigid}
    for c in sorted(weak):  # keep the Kirk joint where a body would be left with under three points
        p = int(par[c])
        points = [sizes[b] + sum(1 for j in range(len(par)) if j not in weak and (j == b or par[j] == b) and par[j] >= 0) for b in (c, p)]
        if min(points) < 3:
            weak.discard(c)
    # A joint between two bodies with poses of their own is placed by the pair fit over those poses (one
    # offset per body for the whole take: sharper under soft tissue than Kirk's free point per frame; swaps
    # and glitches already left out of the poses) when those poses pin it as the sensor path asks of a
    # sensor (PAIR_ROUTE_M); the others by the Kirk fit, which needs no pose.
    kids = {int(c) for c in np.flatnonzero(par >= 0)}
    posed = {c for c in kids if pair_route(exercised, c, int(par[c])) and not noise.rigid}
    pair_jp, pair_rms = pair_joint_points(M, groups, par, sorted(posed), exercised, pick)
    point_jp, point_jrms = point_joint_centres(M, groups, two, par, sorted(pointed), pair_jp)
    pair_jp, pair_rms = {**pair_jp, **point_jp}, {**pair_rms, **point_jrms}
    kirk = kids - posed - pointed
    jp, jrms, base, poses, redo = dict(pair_jp), dict(pair_rms), None, None, None
    for k in range(2):  # second pass: refit without the marker-frames the first pass found wrong
        step(STAGES[2 + k])
        # Not started from the first pass's points: those carry the swaps, and a hinge's point creeps along
        # its axis (a flat valley) from wherever it starts.
        only = kirk if redo is None else kirk & redo
        if noise.rigid:
            new_jp, new_rms, suspects = fixed_joints(work, groups, par, fit_frames, noise, only)
        else:
            new_jp, new_rms, suspects = fit_joints(work, groups, par, fit_frames, joint_groups=pick, only=only)
        jp, jrms = {**jp, **new_jp}, {**jrms, **new_rms}
        strong = {c: v for c, v in jp.items() if c not in weak}
        # Bodies whose markers or joints changed: all of them in the first pass.
        moved = None if redo is None else touched | {int(par[c]) for c in redo} | set(redo)
        shapes = base = skeleton_shapes(work, groups, par, strong, skip=weak, only=moved, previous=base)
        poses = R, t, valid = body_poses(work, shapes, strong, only=moved, previous=poses)
        if weak:
            shapes, jp = add_rigid_route_joints(shapes, weak, par, R, t, valid, jp)
        if k == 1:
            break
        res, thr = robust_marker_residuals(work, shapes, jp)
        # Bodies too small for a rigid check (NaN residual) fall back on the joint-centre test.
        res = np.where(np.isnan(res) & suspects & np.isfinite(work).all(-1), np.inf, res)
        outliers = find_outliers(res, floor_m=thr)
        for start, stop, a, b in outliers.swaps:  # both labels are wrong over the whole span, seen or not
            outliers.mask[start:stop, [a, b]] = True
        if not outliers.mask.any() or (not outliers.swaps and glitch_shift(res, outliers.mask, groups) < REFIT_SHIFT_M):
            break
        work = np.where(outliers.mask[..., None], np.nan, work)
        # Only what the masked marker-frames reach is fitted again: the bodies of swapped markers and those
        # whose fit the masked marker-frames could move (REFIT_SHIFT_M), and the joints to them.
        swapped = {int(x) for sw in outliers.swaps for x in sw[2:]}
        touched = {g for g, grp in enumerate(groups)
                   if swapped & set(grp.tolist()) or glitch_shift(res, outliers.mask, [grp]) >= REFIT_SHIFT_M}
        redo = {int(c) for c in np.flatnonzero(par >= 0) if c in touched or int(par[c]) in touched}
    if noise.rigid:  # each hinge's point on its axis by the sensor path's rule, read from the poses
        jp = hinge_slides(work, shapes, par, R, valid, jp)
        shapes = skeleton_shapes(work, groups, par, jp)
        R, t, valid = body_poses(work, shapes, jp)
    # Poses for every frame, also those thinned out of the joint fits: markers alone, plus joints where fitted.
    bones = bone_lengths(shapes, tree.parent)
    joint_markers = {int(c): pick(int(c), int(par[c])) for c in np.flatnonzero(par >= 0)}
    return OpticalFit(
        kept_names, labels, groups, clus, tree, shapes, bones, jp, jrms, R, t, valid, outliers,
        float(rate_hz), times, unused, exercised, joint_markers, frozenset(posed), frozenset(pointed), noise,
    )  # fmt: skip


def _vec(x) -> list[float] | None:
    x = np.asarray(x, dtype=float)
    return None if not np.isfinite(x).all() else [float(v) for v in x]


def fit_calibration(fit: OpticalFit) -> Calibration:
    """The fit as the solver's `Calibration`: c, l and bones from the Kirk skeleton; singular values, hinge,
    coverage and standard errors from the magnetic pair fit on the derived poses; the marker bodies,
    offsets and swaps as its `optical` extras."""
    from flockcal.solver.accumulator import GramAccumulator
    from flockcal.solver.calibration import Bones, OpticalExtras
    from flockcal.solver.fits import pair_fits

    labels = fit.labels
    parent = fit.tree.parent
    m = len(labels)
    body_of = np.empty(len(fit.marker_names), dtype=int)
    for g, grp in enumerate(fit.groups):
        body_of[grp] = g
    acc = GramAccumulator(m)
    acc.add_poses(fit.rotations, fit.positions, fit.valid)
    kids = [int(c) for c in fit.tree.order if parent[c] >= 0]
    pairs = np.array([[c, parent[c]] for c in kids], dtype=int).reshape(-1, 2)
    pf = pair_fits(acc, pairs)
    cs, ls, rms, eps = [], [], [], []
    for c in kids:
        p = int(parent[c])
        sc, sp_ = fit.shapes[c], fit.shapes[p]
        cc = sc.joint_offsets[sc.joints.index(c)]
        ll = sp_.joint_offsets[sp_.joints.index(c)]
        both = fit.valid[:, c] & fit.valid[:, p]
        e = (
            np.einsum("nij,j->ni", fit.rotations[both, c], cc) + fit.positions[both, c]
            - np.einsum("nij,j->ni", fit.rotations[both, p], ll) - fit.positions[both, p]
        )  # fmt: skip
        sse = float((e**2).sum())
        nb = max(int(both.sum()), 1)
        cs.append(cc)
        ls.append(ll)
        rms.append(float(np.sqrt(sse / nb)))
        eps.append(float(np.sqrt(sse) / nb))
    joints = replace(pf, c=np.array(cs, dtype=float).reshape(-1, 3), l=np.array(ls, dtype=float).reshape(-1, 3),
                     rms=np.array(rms, dtype=float), epsilon=np.array(eps, dtype=float))
    rows = [(b, -1 if f is None else f, t, float(length), bone_stderr(fit, b, f, t)) for b, f, t, length in fit.bones]
    body, frm, to, length, err = (np.array(x).reshape(-1) for x in (zip(*rows) if rows else [()] * 5))
    bones = Bones(body.astype(int), frm.astype(int), to.astype(int), length.astype(float), err.astype(float),
                  body.astype(int) == int(fit.tree.root))
    events = tuple(
        {
            "time_s": float(fit.times[s]),
            "stop_s": float(fit.times[min(e, len(fit.times) - 1)]),
            "markers": [fit.marker_names[a], fit.marker_names[b]],
            "bodies": [labels[body_of[a]], labels[body_of[b]]],
        }
        for s, e, a, b in swap_events(fit)
    )
    extras = OpticalExtras(
        kirk_rms=np.array([float(fit.joint_rms[c]) for c in kids], dtype=float),
        bodies=fit.bodies(),
        markers={
            fit.marker_names[i]: {"body": labels[g], "offset": _vec(fit.shapes[g].marker_offsets[j])}
            for g, grp in enumerate(fit.groups)
            for j, i in enumerate(grp)
        },
        unused_markers=tuple(fit.unused_markers),
        swap_events=events,
        marker_outlier_threshold_m=fit.outliers.threshold_m,
        joint_decisions=tuple(joint_decision(fit.exercised, c, int(parent[c])) for c in kids),
        exercise={**exercise_report(labels, parent, fit.exercised, fit.clustering), **merge_report(fit)},
    )
    placement = np.full((m, 3), np.nan)
    placement[kids] = joints.c
    return Calibration(tuple(labels), int(fit.tree.root), np.asarray(parent), np.asarray(fit.tree.order), int(len(fit.times)),
                       joints, bones, placement, optical=extras)


def merge_why(kind: str, ratio: float, joint_error_m: float, motion_m: float, tolerance_m: float) -> str:
    """One sentence: why two groups of markers were made one body (the verdict of `articulation.judge`)."""
    from flockcal.solver.optical.articulation import JOINT_TOLERANCE_M, ROTATION_MARGIN

    moved = f"moved {1000 * motion_m:.1f} mm against each other"
    if kind == "skin":
        return (f"{moved}, but turned no more than their own markers' soft tissue turns their poses (rotation "
                f"variance {ratio:.1f}× the noise's, under {ROTATION_MARGIN:g}×): skin, not a joint")
    if kind == "twist":
        return (f"{moved}, turning about the line between them: one segment twisting about its length "
                f"(a two-bone forearm, skin rolling about a bone), not a joint between two")
    if kind == "moved":
        err = "not pinned at all" if not np.isfinite(joint_error_m) else f"pinned to {1000 * joint_error_m:.0f} mm only"
        return (f"{moved}, within the {1000 * tolerance_m:g} mm soft tissue reaches; they turned against each "
                f"other ({ratio:.0f}× the noise) but no joint explains it (its centre {err}, over the "
                f"{1000 * JOINT_TOLERANCE_M:g} mm tolerance): kept one body")
    return (f"{moved}, within the {1000 * tolerance_m:g} mm soft tissue reaches; a group of one or two "
            f"markers has no pose to judge a joint by")


def merge_report(fit: OpticalFit) -> dict:
    """The JSON keys that say which groups of markers were merged into one body and why ("merged": per body
    with merges of groups of three or more markers: its rigid parts and each merge's verdict), and which
    markers each joint was fitted on where that is a part of a body ("joints_fitted_on")."""
    names, labels = fit.marker_names, fit.labels
    seg = fit.clustering
    body_of = np.empty(len(names), dtype=int)
    for g, grp in enumerate(fit.groups):
        body_of[grp] = g
    merged: dict[str, dict] = {}
    for mg in seg.merges:
        members = list(mg.a) + list(mg.b)
        g = int(np.bincount(body_of[members]).argmax())
        entry = merged.setdefault(labels[g], {"parts": [[names[i] for i in p] for p in seg.body_parts(g)], "merges": []})
        v = mg.verdict
        entry["merges"].append({
            "groups": [[names[i] for i in mg.a], [names[i] for i in mg.b]],
            "verdict": v.kind,
            "why": merge_why(v.kind, v.rotation_ratio, v.joint_error_m, mg.motion_m, seg.tolerance_m),
            "rotation_ratio": float(v.rotation_ratio) if np.isfinite(v.rotation_ratio) else None,
            "joint_error_m": float(v.joint_error_m) if np.isfinite(v.joint_error_m) else None,
            "relative_motion_m": float(mg.motion_m),
        })
    fitted_on = []
    for c, (mc, mp) in sorted(fit.joint_markers.items()):
        p = int(fit.tree.parent[c])
        if len(mc) < len(fit.groups[c]) or len(mp) < len(fit.groups[p]):
            fitted_on.append({"joint": [labels[c], labels[p]], "child_markers": [names[i] for i in mc],
                              "parent_markers": [names[i] for i in mp]})
    pair_fit = [[labels[c], labels[int(fit.tree.parent[c])]] for c in sorted(fit.pair_route)]
    point = [[labels[c], labels[int(fit.tree.parent[c])]] for c in sorted(fit.point_route)]
    return {"merged": merged, "joints_fitted_on": fitted_on, "pair_fit_joints": pair_fit, "point_joints": point}


def fit_json(fit: OpticalFit) -> dict:
    """The docs/design.md §5 JSON of `fit_calibration(fit)`."""
    return fit_calibration(fit).to_dict()


def swap_events(fit: OpticalFit) -> list[tuple[int, int, int, int]]:
    """Swaps worth telling a person: between two bodies, or inside a body of four or more markers.
    With three markers, which one is wrong cannot be told when another is hidden, so a glitch there is
    masked but not reported."""
    body_of = np.empty(len(fit.marker_names), dtype=int)
    for g, grp in enumerate(fit.groups):
        body_of[grp] = g
    sizes = np.array([len(g) for g in fit.groups])
    return [
        (s, e, a, b)
        for s, e, a, b in fit.outliers.swaps
        if body_of[a] != body_of[b] or sizes[body_of[a]] >= 4
    ]


def bone_stderr(fit: OpticalFit, body: int, a: int | None, b: int) -> float:
    """Standard error of a bone length: spread of the per-frame joint-to-joint distance / √frames."""
    if a is None:
        return float("nan")
    pa, pb = fit.joint_points.get(a), fit.joint_points.get(b)
    if pa is None or pb is None:
        return float("nan")
    d = np.linalg.norm(pa - pb, axis=-1)
    d = d[np.isfinite(d)]
    return float(np.std(d) / np.sqrt(len(d))) if len(d) > 1 else float("nan")
