"""The skeleton's tree from all-pairs fits: minimum spanning tree over residuals, root, rigid groups, loops, ties.

Sensors that never turned relative to each other are contracted into one rigid body first; the MST runs
over bodies (Kruskal's, with strictly positive rank weights so that a perfect fit is still an edge);
non-tree pairs that fit as well as the tree are reported as loop candidates or as ambiguous parents.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from flockcal.solver.errors import SolverError
from flockcal.solver.fits import PairFits
from flockcal.solver.gram_layout import all_pairs_of

# A pair "fits as well as" another when its rms is within this fraction (plus rounding) of the other's.
TIE_FRACTION = 0.05
# Loop candidates: non-tree pairs with rms at most this multiple of the tree's median joint rms.
LOOP_FACTOR = 2.0
# Rigid pairs: no exercised direction, and rms at most this multiple of the typical best-partner rms.
RIGID_FACTOR = 3.0


@dataclass
class Topology:
    root: int
    parent: np.ndarray  # (m,) int, −1 at the root
    order: np.ndarray  # (m,) root first, parents before children
    joint: np.ndarray  # (m,) bool: the link to the parent is a fitted joint (False at the root, rigid members)
    group: np.ndarray  # (m,) rigid-body label; sensors sharing a label never turned relative to each other
    loop_candidates: list = field(default_factory=list)  # [(a, b, rms)]
    rigid_groups: list = field(default_factory=list)  # [[i, …]] groups of two or more sensors
    ambiguous: list = field(default_factory=list)  # [(child, [parents], note)]


def tree_centre(parent_edges: np.ndarray, n_nodes: int, weight=None) -> int:
    """The node whose removal splits a tree (edges (k, 2)) most evenly: smallest largest remaining part.

    Ties go to the node with more neighbours, then the lower index.
    """
    w = np.ones(n_nodes) if weight is None else np.asarray(weight, dtype=float)
    if n_nodes == 1:
        return 0
    e = np.asarray(parent_edges, dtype=np.intp).reshape(-1, 2)
    pred, order = orient(e, n_nodes, 0)
    sub = w.copy()
    for v in order[::-1][:-1]:  # children before parents; at most one pass over the bodies
        sub[pred[v]] += sub[v]
    biggest_child = np.zeros(n_nodes)
    kids = order[1:]
    np.maximum.at(biggest_child, pred[kids], sub[kids])
    score = np.maximum(biggest_child, w.sum() - sub)
    degree = np.bincount(e.ravel(), minlength=n_nodes)
    return int(np.lexsort((np.arange(n_nodes), -degree, score))[0])


def orient(edges: np.ndarray, n: int, root: int) -> tuple[np.ndarray, np.ndarray]:
    """Parent array and BFS order of the tree `edges` (k, 2) hung from `root`.

    A plain breadth-first walk: for trees of tens of bodies it is cheaper than building a sparse graph.
    """
    nbrs: list[list[int]] = [[] for _ in range(n)]
    for a, b in np.asarray(edges, dtype=np.intp).reshape(-1, 2).tolist():
        nbrs[a].append(b)
        nbrs[b].append(a)
    parent = np.full(n, -1, dtype=np.intp)
    seen = [False] * n
    seen[root] = True
    order = [root]
    for x in order:  # the list grows while we walk it
        for y in nbrs[x]:
            if not seen[y]:
                seen[y] = True
                parent[y] = x
                order.append(y)
    if len(order) != n:
        raise SolverError("the tree does not reach every sensor")
    return parent, np.array(order, dtype=np.intp)


def ancestors(parent: np.ndarray, order: np.ndarray) -> np.ndarray:
    """(m, m) bool: anc[x, y] is True when y is a proper ancestor of x."""
    m = len(parent)
    anc = np.zeros((m, m), dtype=bool)
    for x in order[1:]:  # parents come first, so each row copies a finished one
        p = parent[x]
        anc[x] = anc[p]
        anc[x, p] = True
    return anc


# The live service refits ~30×/s and the tree rarely changes between refits: the two graph steps are
# memoised on their exact inputs (the rigid mask; the links with their rank-order weights), so a result is
# only reused for an identical graph.
@lru_cache(maxsize=16)
def rigid_bodies(rigid: bytes, m: int) -> tuple[int, np.ndarray]:
    """(number of rigid bodies, body label per sensor) of an (m, m) bool "never turned" matrix given as
    bytes, so refits that find the same rigid pairs hit the cache.

    The connected components, labelled in the order of each one's lowest sensor (as csgraph's
    `connected_components` labels them), by a search in plain Python: on a few dozen sensors that is
    microseconds, where importing scipy.sparse cost every `flockcal fit` ~0.05 s."""
    linked = np.frombuffer(rigid, dtype=bool).reshape(m, m)
    linked = linked | linked.T
    label = np.full(m, -1, dtype=np.int32)
    n_groups = 0
    for start in range(m):
        if label[start] >= 0:
            continue
        label[start] = n_groups
        todo = [start]
        while todo:
            x = todo.pop()
            for y in np.flatnonzero(linked[x] & (label < 0)).tolist():
                label[y] = n_groups
                todo.append(y)
        n_groups += 1
    label.setflags(write=False)
    return n_groups, label


@lru_cache(maxsize=16)
def _tree_links(n_groups: int, gi: bytes, gj: bytes, weights: bytes) -> np.ndarray:
    """Which links (gi, gj) the minimum spanning tree (forest, if the links do not connect every body)
    over these weights uses.

    Kruskal's, in plain Python: the weights are distinct ranks, so the minimum spanning forest is unique
    and this is the tree csgraph's `minimum_spanning_tree` finds, at a tenth of its cost on 16 bodies
    (its sparse set-up alone was a fifth of a live refit, and the rank order changes often enough that
    the memo above misses on many refits)."""
    a, b, w = np.frombuffer(gi, dtype=np.intp), np.frombuffer(gj, dtype=np.intp), np.frombuffer(weights)
    root = list(range(n_groups))

    def find(x: int) -> int:
        while root[x] != x:
            root[x] = root[root[x]]
            x = root[x]
        return x

    used = np.zeros(len(a), dtype=bool)
    joined = 0
    for k in np.argsort(w, kind="stable").tolist():
        ra, rb = find(int(a[k])), find(int(b[k]))
        if ra != rb:
            root[ra] = rb
            used[k] = True
            joined += 1
            if joined == n_groups - 1:
                break
    used.setflags(write=False)
    return used


@dataclass(frozen=True)
class _Hung:
    """Everything that follows from the tree's links and the root alone (read-only arrays; see `_hang`)."""

    root: int
    parent: np.ndarray
    order: np.ndarray
    is_joint: np.ndarray
    rigid_groups: tuple  # ((i, …), …) groups of two or more sensors
    jc: np.ndarray  # the joint children, ascending
    unlinked: np.ndarray  # (m(m−1)/2,) over all_pairs: the two sensors are in bodies the tree does not link
    may_tie: np.ndarray  # (len(jc), m): sensors that could be another parent of each joint child


@lru_cache(maxsize=16)
def _hang(m: int, n_groups: int, label_b: bytes, edges_b: bytes, root: int) -> _Hung:
    """The tree over sensors from the bodies' joint links (k, 2), hung from `root` (−1: the centre body).

    Memoised like the graph steps: between refits the links and root rarely change, and the Python walks
    here (orientation, ancestors, groups) cost more than the float work that remains per refit.
    """
    label = np.frombuffer(label_b, dtype=np.intp)
    joint_edges = np.frombuffer(edges_b, dtype=np.intp).reshape(-1, 2)
    gedges = label[joint_edges]
    if root < 0:  # the body that splits the tree most evenly
        rg = tree_centre(gedges, n_groups, np.bincount(label, minlength=n_groups))
        root = int(np.flatnonzero(label == rg)[0])

    # Within a rigid body every member hangs from the member where the body's inboard joint attaches.
    gparent, _ = orient(gedges, n_groups, label[root])
    entry = np.full(n_groups, -1)
    entry[label[root]] = root
    jparent = np.full(m, -1)
    a, b = joint_edges[:, 0], joint_edges[:, 1]
    a_is_child = gparent[label[a]] == label[b]
    child, par = np.where(a_is_child, a, b), np.where(a_is_child, b, a)
    entry[label[child]] = child
    jparent[child] = par
    parent = np.full(m, -1, dtype=np.intp)
    is_joint = jparent >= 0
    parent[is_joint] = jparent[is_joint]
    members = (np.arange(m) != entry[label]) & (np.arange(m) != root)
    parent[members] = entry[label[members]]
    parent[root] = -1
    edges = np.stack([np.flatnonzero(parent >= 0), parent[parent >= 0]], axis=1)
    _, order = orient(edges, m, root)

    groups: list[list[int]] = [[] for _ in range(n_groups)]
    for i, g in enumerate(label.tolist()):
        groups[g].append(i)

    # Loop candidates can only join bodies that the tree does not link directly.
    jc = np.flatnonzero(is_joint)
    linked = np.zeros((n_groups, n_groups), dtype=bool)
    linked[label[jc], label[parent[jc]]] = linked[label[parent[jc]], label[jc]] = True
    iu, ju = all_pairs_of(m).T
    unlinked = (label[iu] != label[ju]) & ~linked[label[iu], label[ju]]

    # Another parent of a joint child: a sensor not below the child, in neither the child's nor its parent's body.
    anc = ancestors(parent, order)
    may_tie = ~anc.T[jc] & (label[None, :] != label[jc][:, None]) & (label[None, :] != label[parent[jc]][:, None])

    for x in (parent, order, is_joint, jc, unlinked, may_tie):
        x.setflags(write=False)
    return _Hung(int(root), parent, order, is_joint, tuple(tuple(g) for g in groups if len(g) > 1), jc, unlinked,
                 may_tie)


def _squares(fits: PairFits, m: int) -> np.ndarray:
    """`fits.square` of "n", "rms", "rank", "rms_floor", "determined" and "hinge" (filled 0, inf, 0, 0, 0,
    0), in one scatter: (6, m, m)."""
    out = np.empty((6, m, m))
    out[...] = np.array([0.0, np.inf, 0.0, 0.0, 0.0, 0.0])[:, None, None]
    v = np.stack([fits.n, fits.rms, fits.rank, fits.rms_floor, fits.determined, fits.hinge]).astype(float)
    out[:, fits.pairs[:, 0], fits.pairs[:, 1]] = v
    out[:, fits.pairs[:, 1], fits.pairs[:, 0]] = v
    return out


def _median(x: np.ndarray) -> float:
    """np.median of a short 1-D array without its generic machinery (the same value, a few times faster)."""
    s = np.sort(x)
    h = len(s) // 2
    return float(s[h]) if len(s) % 2 else float((s[h - 1] + s[h]) / 2.0)


def spanning_tree(fits: PairFits, n_sensors: int, root: int | None = None) -> Topology:
    """The skeleton tree over all sensors from fits of (ideally) all pairs, hung from `root` (auto if None)."""
    m = int(n_sensors)
    if root is not None and not 0 <= int(root) < m:
        raise SolverError(f"root index {root} is out of range for {m} sensors")
    n, rms, rank, floor, determined, hinge = _squares(fits, m)
    determined, hinge = determined > 0, hinge > 0
    measured = n > 0
    np.fill_diagonal(measured, False)
    rms = np.where(measured, rms, np.inf)
    tol = np.nan_to_num(floor) + 1e-12  # rms below this is 0 to rounding
    best = np.min(rms, axis=1)
    found = np.isfinite(best)
    scale = _median(best[found]) if found.any() else 0.0

    # Rigid bodies: pairs that never turned relative to each other beyond noise, yet fit like a joint would.
    rigid = measured & (rank <= 3) & (rms <= RIGID_FACTOR * scale + tol)
    n_groups, label = rigid_bodies(rigid.tobytes(), m)

    # Contracted graph: each pair of bodies is linked by its best-fitting sensor pair.
    upper = all_pairs_of(m)
    iu, ju = upper.T
    rms_u = rms[iu, ju]
    cross = label[iu] != label[ju]
    cross_pairs, pr = upper[cross], rms_u[cross]
    pi, pj = cross_pairs.T
    gi, gj = np.minimum(label[pi], label[pj]), np.maximum(label[pi], label[pj])
    srt = np.lexsort((pr, gj, gi))  # within each body pair, best rms first
    first = np.ones(len(srt), dtype=bool)
    first[1:] = (gi[srt][1:] != gi[srt][:-1]) | (gj[srt][1:] != gj[srt][:-1])
    link = srt[first]
    lw = pr[link]
    # csgraph reads a zero weight as "no edge": feed rank order (1, 2, …), unmeasured pairs last.
    finite = np.isfinite(lw)
    weights = np.empty(len(link))
    weights[np.argsort(np.where(finite, lw, np.inf), kind="stable")] = np.arange(1, len(link) + 1)
    used = _tree_links(n_groups, gi[link].astype(np.intp).tobytes(), gj[link].astype(np.intp).tobytes(), weights.tobytes())
    joint_edges = cross_pairs[link[used]]
    if n_groups > 1 and len(joint_edges) != n_groups - 1:
        raise SolverError("the sensors do not form one connected skeleton")

    # Root (the user's sensor, or the body that splits the tree most evenly) and the tree hung from it.
    h = _hang(m, n_groups, label.astype(np.intp).tobytes(), joint_edges.astype(np.intp).tobytes(),
              -1 if root is None else int(root))
    parent = h.parent.copy()
    topo = Topology(h.root, parent, h.order.copy(), h.is_joint.copy(), label)
    topo.rigid_groups = [list(g) for g in h.rigid_groups]

    # Loop candidates: pairs between bodies not linked by the tree that fit like its joints.
    jc = h.jc
    tree_rms = rms[jc, parent[jc]]
    tree_rms = tree_rms[np.isfinite(tree_rms)]
    if len(tree_rms):
        limit = LOOP_FACTOR * _median(tree_rms)
        cand = h.unlinked & (rms_u <= limit + tol[iu, ju]) & determined[iu, ju]
        topo.loop_candidates = [(int(a), int(b), float(rms[a, b])) for a, b in zip(iu[cand], ju[cand])]

    # Ambiguous parents: another body, not below the child, that the child's sensor fits as well as its parent.
    if len(jc):
        ref = rms[jc, parent[jc]]
        alt = h.may_tie & (rms[jc] <= ref[:, None] * (1 + TIE_FRACTION) + tol[jc] + tol[jc, parent[jc]][:, None])
        alt &= np.isfinite(rms[jc])
        unmeasured = ~np.isfinite(ref)
        for r in np.flatnonzero(unmeasured | alt.any(axis=1)):  # usually none: no loop over every joint
            x, p = int(jc[r]), int(parent[jc[r]])
            others = np.flatnonzero(alt[r])
            if unmeasured[r]:
                topo.ambiguous.append((x, [p], "no frame has both sensors valid: this joint was never measured"))
            else:
                hinged = hinge[x, p] or hinge[x, others].any()
                note = "intersecting hinge axes" if hinged else "coincident joint centres"
                topo.ambiguous.append((x, [p] + [int(q) for q in others], f"fits equally well to each: {note}"))
    return topo
