"""Which joints an optical take exercised, decided as the sensor path decides (design.md §3a), and the
skeleton forest over those joints only: a body no exercised joint reaches hangs from nothing.

Bodies with a frame of their own (three or more markers) get their poses from their markers alone; the
pair fits over those poses (`flockcal.solver.fits.pair_fits`: batch-means standard errors, so soft tissue
correlated in time does not pass for precision) say whether each pair's joint centre is pinned.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flockcal.solver.optical.joints import Tree, joint_point
from flockcal.solver.optical.rigid import apply, procrustes_mean, rigid_fit
from flockcal.solver.optical.segmentation import RIGID_TOLERANCE_M

FRAMED = 3  # markers a body needs for a pose of its own

# The sensor path's rule with the sensor path's tolerance scaled to skin markers: a marker cluster's pose
# carries the soft tissue's 5–15 mm, so a centre pinned within 10 mm along every direction (or a hinge whose
# axis moves it at most that) counts as exercised. Real trials sit on either side of it by a margin: the
# joints a trial moved come out at ≤ 9 mm, the ones it did not at ≥ 15 mm (docs/optical.md).
TOLERANCE_M = 0.010

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

    def candidate(self) -> np.ndarray:
        """(G, G) pairs that may be a tree edge: determined, or not judgeable from poses (a body of two
        markers is left to the Kirk fit). A lone marker is no candidate: it has no orientation, so neither
        the pair fits nor the Kirk fit (whose point can sit on the marker itself) can judge a joint to it."""
        two = self.sizes >= 2
        c = (self.determined | ~self.judged) & two[:, None] & two[None, :]
        np.fill_diagonal(c, False)
        return c


def marker_poses(markers: np.ndarray, groups: list[np.ndarray]):
    """Per-body rotations (n, G, 3, 3), positions (n, G, 3), valid (n, G) from each framed body's own
    markers (generalised Procrustes shape, Kabsch per frame), label swaps and glitches left out."""
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


def judge_pairs(markers: np.ndarray, groups: list[np.ndarray], tolerance_m: float | None = None) -> Exercised:
    """Pair fits over the bodies' marker-only poses, and which joints they determine (design.md §3a)."""
    from flockcal.solver.accumulator import GramAccumulator
    from flockcal.solver.fits import all_pairs, pair_fits

    G = len(groups)
    R, t, valid = marker_poses(markers, groups)
    framed = valid.sum(0) >= 10
    determined = np.zeros((G, G), dtype=bool)
    judged = framed[:, None] & framed[None, :]
    np.fill_diagonal(judged, False)
    hinge = np.zeros((G, G), dtype=bool)
    rms = np.full((G, G), np.nan)
    derr = np.full((G, G, 3), np.inf)
    if G >= 2 and judged.any():
        acc = GramAccumulator(G)
        acc.update(R, t, valid)
        P = all_pairs(G)
        P = P[judged[P[:, 0], P[:, 1]]]
        pf = pair_fits(acc, P, tolerance=TOLERANCE_M if tolerance_m is None else tolerance_m)
        a, b = P[:, 0], P[:, 1]
        determined[a, b] = determined[b, a] = pf.determined
        hinge[a, b] = hinge[b, a] = pf.hinge
        rms[a, b] = rms[b, a] = pf.rms
        derr[a, b] = derr[b, a] = pf.direction_error
    sizes = np.array([len(g) for g in groups])
    return Exercised(framed, sizes, determined, judged, hinge, rms, derr, R, t, valid)


def candidate_costs(
    markers: np.ndarray, groups: list[np.ndarray], frames: np.ndarray, candidate: np.ndarray, penalty: float = 1e-5
) -> np.ndarray:
    """(G, G) Kirk joint-point residual rms of the candidate pairs on `frames`; inf elsewhere (no edge)."""
    G = len(groups)
    cost = np.full((G, G), np.inf)
    for a, b in zip(*np.nonzero(np.triu(candidate, 1))):
        fit = joint_point(markers[:, groups[a]], markers[:, groups[b]], penalty=penalty, frames=frames, max_iter=15)
        cost[a, b] = cost[b, a] = fit.rms
    return cost


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
