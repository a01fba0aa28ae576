"""Which joints an optical take exercised, decided as the sensor path decides (design.md §3a), and the
skeleton forest over those joints only: a body no exercised joint reaches hangs from nothing.

Bodies with a frame of their own (three or more markers) get their poses from their markers alone; the
pair fits over those poses (`flockcal.solver.fits.pair_fits`: batch-means standard errors, so soft tissue
correlated in time does not pass for precision) say whether each pair's joint centre is pinned.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from flockcal.solver.optical.articulation import JOINT_TOLERANCE_M as TOLERANCE_M
from flockcal.solver.optical.joints import Tree, joint_point
from flockcal.solver.optical.kirk_batch import shared_poses
from flockcal.solver.optical.rigid import apply, procrustes_mean, rigid_fit
from flockcal.solver.optical.segmentation import RIGID_TOLERANCE_M

FRAMED = 3  # markers a body needs for a pose of its own

# A marker this many times its body's median fit residual off the body's shape (and beyond the rigid
# tolerance) is a label swap or glitch in that frame, not soft tissue.
OUTLIER_FACTOR = 5.0


@dataclass(frozen=True)
class Exercised:
    """Pair decisions over the bodies: arrays (G, G), symmetric."""

    framed: np.ndarray  # (G,) bool: the body has a pose from its markers alone
    sizes: np.ndarray  # (G,) markers per body
    determined: np.ndarray  # (G, G) bool: the pair fit pins the joint centre (ball or hinge)
    judged: np.ndarray  # (G, G) bool: both bodies framed, so the pair fit decided
    hinge: np.ndarray  # (G, G) bool: determined as a hinge (one free direction, its axis pinned)
    rms: np.ndarray  # (G, G) m: the pair fit's residual (NaN where not judged)
    direction_error: np.ndarray  # (G, G, 3) m: the centre's error along the three least-turned directions
    rotations: np.ndarray  # (n, G, 3, 3) marker-only poses (identity where not valid)
    positions: np.ndarray  # (n, G, 3)
    valid: np.ndarray  # (n, G)
    shapes: dict | None = None  # {g: (q, 3) body g's mean shape, the frame of its pose}

    def candidate(self) -> np.ndarray:
        """(G, G) pairs that may be a tree edge: determined, or not judgeable from poses (a body of two
        markers is left to the Kirk fit). A lone marker is no candidate: it has no orientation, so neither
        the pair fits nor the Kirk fit (whose point can sit on the marker itself) can judge a joint to it."""
        two = self.sizes >= 2
        c = (self.determined | ~self.judged) & two[:, None] & two[None, :]
        np.fill_diagonal(c, False)
        return c


def marker_poses(markers: np.ndarray, groups: list[np.ndarray], shapes: dict | None = None):
    """Per-body rotations (n, G, 3, 3), positions (n, G, 3), valid (n, G) from each framed body's own
    markers (generalised Procrustes shape, Kabsch per frame), label swaps and glitches left out; each
    framed body's shape goes into `shapes` when given."""
    n = markers.shape[0]
    G = len(groups)
    R = np.tile(np.eye(3), (n, G, 1, 1))
    t = np.zeros((n, G, 3))
    valid = np.zeros((n, G), dtype=bool)
    for g, idx in enumerate(groups):
        if len(idx) < FRAMED:
            continue
        pts = markers[:, idx]
        shape, Rg, tg, ok = procrustes_mean(pts)
        if shapes is not None:
            shapes[g] = shape
        # A swapped or glitching label sits centimetres off the shape; soft tissue stays within the
        # segmentation's tolerance. Such marker-frames are dropped and the frame refitted once.
        res = np.linalg.norm(apply(Rg, tg, shape) - pts, axis=-1)
        fin = res[ok & np.isfinite(res).all(1)] if ok.any() else res[:0]
        limit = max(OUTLIER_FACTOR * float(np.median(fin)) if fin.size else 0.0, RIGID_TOLERANCE_M)
        bad = (res > limit) & np.isfinite(res)
        if bad.any():
            Rg, tg, ok = rigid_fit(shape, np.where(bad[..., None], np.nan, pts))
        R[ok, g], t[ok, g], valid[:, g] = Rg[ok], tg[ok], ok
    return R, t, valid


def judge_pairs(markers: np.ndarray, groups: list[np.ndarray], tolerance_m: float | None = None,
                joint_groups: Callable[[int, int], tuple[np.ndarray, np.ndarray]] | None = None) -> Exercised:
    """Pair fits over the bodies' marker-only poses, and which joints they determine (design.md §3a).
    `joint_groups(a, b)` gives the markers of a and of b a joint between them is judged on (a body that
    absorbed several segments: its rigid part next to the other body); default the whole bodies."""
    from flockcal.solver.accumulator import GramAccumulator
    from flockcal.solver.fits import pair_fits

    G = len(groups)
    pick = joint_groups or (lambda a, b: (groups[a], groups[b]))
    shapes: dict = {}
    R, t, valid = marker_poses(markers, groups, shapes)
    # Each pair's two marker sets; the distinct sets are the "sensors" of one accumulator.
    sets: dict[tuple, int] = {}
    pair_sets = {}
    for a in range(G):
        for b in range(a + 1, G):
            ia, ib = pick(a, b)
            pair_sets[a, b] = tuple(sets.setdefault(tuple(int(i) for i in x), len(sets)) for x in (ia, ib))
    whole = {tuple(int(i) for i in g): k for k, g in enumerate(groups)}
    extra_keys = [key for key in sets if key not in whole]
    Rx, tx, vx = marker_poses(markers, [np.array(key) for key in extra_keys]) if extra_keys else (R, t, valid)
    SR = np.empty((len(markers), len(sets), 3, 3))
    St = np.empty((len(markers), len(sets), 3))
    Sv = np.empty((len(markers), len(sets)), dtype=bool)
    for key, k in sets.items():
        src, j = ((R, t, valid), whole[key]) if key in whole else ((Rx, tx, vx), extra_keys.index(key))
        SR[:, k], St[:, k], Sv[:, k] = src[0][:, j], src[1][:, j], src[2][:, j]
    framed = valid.sum(0) >= 10
    determined = np.zeros((G, G), dtype=bool)
    judged = framed[:, None] & framed[None, :]
    np.fill_diagonal(judged, False)
    hinge = np.zeros((G, G), dtype=bool)
    rms = np.full((G, G), np.nan)
    derr = np.full((G, G, 3), np.inf)
    if G >= 2 and judged.any():
        acc = GramAccumulator(len(sets))
        acc.add_poses(SR, St, Sv)
        body_pairs = np.array([(a, b) for (a, b) in pair_sets if judged[a, b]], dtype=int).reshape(-1, 2)
        P = np.array([pair_sets[a, b] for a, b in body_pairs], dtype=int).reshape(-1, 2)
        pf = pair_fits(acc, P, tolerance=TOLERANCE_M if tolerance_m is None else tolerance_m)
        a, b = body_pairs[:, 0], body_pairs[:, 1]
        determined[a, b] = determined[b, a] = pf.determined
        hinge[a, b] = hinge[b, a] = pf.hinge
        rms[a, b] = rms[b, a] = pf.rms
        derr[a, b] = derr[b, a] = pf.direction_error
    sizes = np.array([len(g) for g in groups])
    return Exercised(framed, sizes, determined, judged, hinge, rms, derr, R, t, valid, shapes)


def candidate_costs(
    markers: np.ndarray, groups: list[np.ndarray], frames: np.ndarray, candidate: np.ndarray, penalty: float = 1e-5,
    joint_groups: Callable[[int, int], tuple[np.ndarray, np.ndarray]] | None = None,
    exercised: Exercised | None = None, points: np.ndarray | None = None,
) -> np.ndarray:
    """(G, G) cost of every candidate pair, inf elsewhere (no edge): the pair fit's residual rms where both
    bodies have a pose (`exercised.judged`), else the Kirk joint-point residual rms on `frames`, each kind
    over its own scale (`on_own_scale`). `joint_groups` as in `judge_pairs`.

    The pair fit holds one offset per body for the whole take, so a pair with no joint between them leaves
    centimetres (16–220 mm on the simulated walk, its true joints 3–7 mm); Kirk's point is free in every
    frame and fits almost any two groups to a few millimetres, so it only decides where no pose can.
    `points` (G, G): the residual of the point joint (`two_marker`) where judged (finite), before the
    others: a take with bodies of two markers has its costs of this one kind wherever a body has a pose."""
    G = len(groups)
    pick = joint_groups or (lambda a, b: (groups[a], groups[b]))
    cost = np.full((G, G), np.inf)
    poses = shared_poses()  # one group's pose on these frames, shared by all its pairs
    for a, b in zip(*np.nonzero(np.triu(candidate, 1))):
        if points is not None and np.isfinite(points[a, b]):
            cost[a, b] = cost[b, a] = points[a, b]
            continue
        if exercised is not None and exercised.judged[a, b] and np.isfinite(exercised.rms[a, b]):
            cost[a, b] = cost[b, a] = exercised.rms[a, b]
            continue
        ia, ib = pick(int(a), int(b))
        fit = joint_point(markers[:, ia], markers[:, ib], penalty=penalty, frames=frames, max_iter=15, poses=poses)
        cost[a, b] = cost[b, a] = fit.rms
    if exercised is None:
        return cost
    kind = np.where(exercised.judged & np.isfinite(exercised.rms), 1, 0)
    if points is not None:
        kind = np.where(np.isfinite(points), 2, kind)
    return on_own_scale(cost, kind)


def on_own_scale(cost: np.ndarray, kind: np.ndarray) -> np.ndarray:
    """`cost` with the pairs of each kind (`kind`: 1 pair fit, 2 point joint, 0 Kirk; a bool array: pair fit
    or Kirk) divided by that kind's typical true-joint residual: the median over bodies of their cheapest
    pair of the kind (a body's cheapest pair is its joint in all but the rare case). The residuals differ in
    size (the pair fit's is a 3-D error with one offset for the take, a point joint's and Kirk's distance
    errors, Kirk's with a free point per frame); over their own scales they compare, so a spanning tree can
    use them all."""
    out = cost.copy()
    kind = np.asarray(kind).astype(int)
    for mask in (kind == k for k in np.unique(kind)):
        c = np.where(mask, cost, np.inf)
        np.fill_diagonal(c, np.inf)
        best = c.min(axis=1)
        best = best[np.isfinite(best) & (best > 0)]
        if best.size:
            out[mask] = cost[mask] / float(np.median(best))
    return out


def spanning_forest(cost: np.ndarray, sizes: np.ndarray, root: int | None = None) -> Tree:
    """Minimum spanning forest over the finite pair costs (inf: no edge). Each part hangs from its body
    with the most markers (the trunk, in a person; ties go to the most central body), or from `root` in
    its part; the part holding `root` (else the one with most markers) comes first, and its root is
    `Tree.root`. Prim's algorithm on the dense matrix: bodies are tens, and scipy's csgraph import alone
    would cost more than the whole tree."""
    G = len(cost)
    adj = np.zeros((G, G), dtype=bool)
    part = np.full(G, -1)
    for start in range(G):
        if part[start] >= 0:
            continue
        label = int(part.max()) + 1
        part[start] = label
        best = np.where(part < 0, cost[start], np.inf)
        via = np.full(G, start)
        while np.isfinite(best).any():
            h = int(np.argmin(best))
            adj[h, via[h]] = adj[via[h], h] = True
            part[h] = label
            closer = (cost[h] < best) & (part < 0)
            best = np.where(closer, cost[h], best)
            via = np.where(closer, h, via)
            best[part >= 0] = np.inf
    n_parts = int(part.max()) + 1
    counts = np.bincount(part, weights=sizes, minlength=n_parts)
    first = part[root] if root is not None else int(np.argmax(counts))
    parent = np.full(G, -1)
    order: list[int] = []
    main_root = None
    for c in [first] + [c for c in np.argsort(-counts, kind="stable") if c != first]:
        members = np.flatnonzero(part == c)
        if root is not None and c == part[root]:
            r = int(root)
        else:
            biggest = members[sizes[members] == sizes[members].max()]
            r = min(biggest, key=lambda g: (largest_branch(adj, members, g), g))
        main_root = int(r) if main_root is None else main_root
        order.append(int(r))
        frontier, seen = [int(r)], {int(r)}
        while frontier:
            nxt = []
            for g in frontier:
                for h in np.flatnonzero(adj[g]):
                    if int(h) not in seen:
                        parent[h] = g
                        seen.add(int(h))
                        order.append(int(h))
                        nxt.append(int(h))
            frontier = nxt
    return Tree(parent, int(main_root), cost, order)


def largest_branch(adj: np.ndarray, members: np.ndarray, g: int) -> int:
    """Bodies in the largest piece of `members`' tree left when body `g` is taken out (smaller: more central)."""
    left = set(int(x) for x in members) - {int(g)}
    largest = 0
    while left:
        stack = [left.pop()]
        size = 1
        while stack:
            x = stack.pop()
            for y in np.flatnonzero(adj[x]):
                if int(y) in left:
                    left.discard(int(y))
                    stack.append(int(y))
                    size += 1
        largest = max(largest, size)
    return largest


def exercise_report(labels, parent: np.ndarray, exercised: Exercised | None, segmentation=None) -> dict:
    """The JSON keys that say what the take exercised: `exercised_joints` (tree joints [child, parent]
    the pair fits determined), `kirk_only_joints` (tree joints to a body without a frame of its own,
    which the pair fits cannot judge), `unjoined` (bodies no exercised joint reaches), the tolerances
    used, and each body's internal relative motion (m)."""
    kids = [int(c) for c in np.flatnonzero(parent >= 0)]
    judged = (lambda c: bool(exercised.judged[c, parent[c]])) if exercised is not None else (lambda c: False)
    touched = set(kids) | {int(parent[c]) for c in kids}
    out = {
        "exercised_joints": [[labels[c], labels[parent[c]]] for c in kids if judged(c)],
        "kirk_only_joints": [[labels[c], labels[parent[c]]] for c in kids if not judged(c)],
        "unjoined": [labels[g] for g in range(len(labels)) if g not in touched],
        "joint_tolerance_m": TOLERANCE_M,
    }
    if segmentation is not None:
        out["rigid_tolerance_m"] = float(segmentation.tolerance_m)
        out["body_motion_m"] = {labels[g]: float(v) for g, v in enumerate(segmentation.internal_motion)}
    return out


def joint_decision(exercised: Exercised | None, child: int, parent: int) -> dict:
    """`determined` (None: not judgeable from poses) and `direction_error_m` for one tree joint's JSON."""
    if exercised is None or not exercised.judged[child, parent]:
        return {"determined": None, "direction_error_m": None}
    err = exercised.direction_error[child, parent]
    return {
        "determined": bool(exercised.determined[child, parent]),
        "direction_error_m": [float(e) if np.isfinite(e) else None for e in err],
    }
