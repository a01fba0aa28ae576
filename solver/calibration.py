"""A whole-skeleton calibration from one accumulator: topology (searched or given), tree joints, bones, placement.

`calibrate` is what `flockcal fit` and the live server call (≥30×/s): all-pair fits, MST and the tree's
joints are array operations; `Calibration.to_dict()` is exactly the JSON of design.md §5.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components

from flockcal.solver.errors import SolverError
from flockcal.solver.fits import PairFits, pair_fits
from flockcal.solver.topology import _orient, spanning_tree


@dataclass(frozen=True)
class Bones:
    """Distances between two joint centres of one body, in that body's frame (design.md §5)."""

    body: np.ndarray  # (B,) sensor index of the body (for a rigid group: the member holding its inboard joint)
    from_joint: np.ndarray  # (B,) child index of the inboard joint, or of the first outboard joint at the root
    to_joint: np.ndarray  # (B,) child index of the outboard joint
    length: np.ndarray  # (B,) m
    stderr: np.ndarray  # (B,) m
    at_root: np.ndarray  # (B,) bool: between two outboard joints of the root body (no inboard joint)

    def __len__(self) -> int:
        return len(self.body)


@dataclass
class Calibration:
    names: tuple
    root: int
    parent: np.ndarray  # (m,) int, −1 at the root
    order: np.ndarray  # (m,) root first
    frames: int
    joints: PairFits  # tree joints as (child, parent) pairs, in `order`
    bones: Bones
    placement: np.ndarray  # (m, 3) each sensor's offset from its inboard joint, in its own frame (NaN at root)
    loop_candidates: list = field(default_factory=list)  # [(a, b, rms)]
    rigid_groups: list = field(default_factory=list)  # [[i, …]]
    ambiguous: list = field(default_factory=list)  # [(child, [parents], note)]
    fits: PairFits | None = None  # all pairs, when the topology was searched
    hierarchy_given: bool = False

    # Joint arrays, named as the JSON names them.
    @property
    def joint_child(self) -> np.ndarray:
        return self.joints.pairs[:, 0]

    @property
    def joint_parent(self) -> np.ndarray:
        return self.joints.pairs[:, 1]

    c = property(lambda self: self.joints.c)
    l = property(lambda self: self.joints.l)
    rms = property(lambda self: self.joints.rms)
    epsilon = property(lambda self: self.joints.epsilon)
    singular_values = property(lambda self: self.joints.singular_values)
    hinge = property(lambda self: self.joints.hinge)
    axis_child = property(lambda self: self.joints.axis_i)
    axis_parent = property(lambda self: self.joints.axis_j)
    coverage = property(lambda self: self.joints.coverage)
    c_stderr = property(lambda self: self.joints.c_stderr)
    l_stderr = property(lambda self: self.joints.l_stderr)

    @property
    def n_sensors(self) -> int:
        return len(self.names)

    def parent_map(self) -> dict:
        """{child name: parent name} for every sensor but the root."""
        return {self.names[i]: self.names[p] for i, p in enumerate(self.parent) if p >= 0}

    def to_dict(self, slip_events=None) -> dict:
        """The `flockcal fit --json` object of design.md §5; `slip_events` is filled by the slippage detector.

        Extends the contract with "rigid_groups" (names of sensors that never turned relative to each other)
        and "ambiguous" (children with more than one equally good parent). NaN becomes null.
        """
        nm = self.names
        j = self.joints
        joints = []
        for k in range(len(j)):
            joints.append({
                "child": nm[j.pairs[k, 0]],
                "parent": nm[j.pairs[k, 1]],
                "c": _vec(j.c[k]),
                "l": _vec(j.l[k]),
                "rms_m": _num(j.rms[k]),
                "epsilon": _num(j.epsilon[k]),
                "singular_values": _vec(j.singular_values[k]),
                "hinge": bool(j.hinge[k]),
                "axis_child": _vec(j.axis_i[k]) if j.hinge[k] else None,
                "axis_parent": _vec(j.axis_j[k]) if j.hinge[k] else None,
                "coverage": _vec(j.coverage[k]),
                "c_stderr_m": _num(j.c_stderr[k]),
                "l_stderr_m": _num(j.l_stderr[k]),
            })
        b = self.bones
        bones = [{
            "body": nm[b.body[k]],
            "from_joint": nm[b.from_joint[k]] if b.from_joint[k] >= 0 else None,
            "to_joint": nm[b.to_joint[k]],
            "length_m": _num(b.length[k]),
            "stderr_m": _num(b.stderr[k]),
        } for k in range(len(b))]
        return {
            "sensors": list(nm),
            "root": nm[self.root],
            "parent": self.parent_map(),
            "frames": int(self.frames),
            "joints": joints,
            "bones": bones,
            "loop_candidates": [{"a": nm[a], "b": nm[bb], "rms_m": _num(r)} for a, bb, r in self.loop_candidates],
            "slip_events": list(slip_events or []),
            "rigid_groups": [[nm[i] for i in g] for g in self.rigid_groups],
            "ambiguous": [{"child": nm[c], "parents": [nm[p] for p in ps], "note": note} for c, ps, note in self.ambiguous],
        }


def _num(x) -> float | None:
    x = float(x)
    return x if np.isfinite(x) else None


def _vec(v) -> list:
    return [_num(x) for x in np.asarray(v).ravel()]


def _index(name, names: Sequence[str], what: str) -> int:
    if isinstance(name, (int, np.integer)) and not isinstance(name, bool):
        if 0 <= int(name) < len(names):
            return int(name)
        raise SolverError(f"{what}: sensor index {name} is out of range (0..{len(names) - 1})")
    try:
        return list(names).index(str(name))
    except ValueError:
        raise SolverError(f"{what}: unknown sensor {name!r} (the take has: {', '.join(names)})") from None


def parse_hierarchy(hierarchy, names: Sequence[str]) -> np.ndarray:
    """A parent index array (−1 at the root) from a {child: parent} map (names or indices, root omitted or
    mapped to None) or from a parent array; SolverError naming the problem for anything that is not one tree.
    """
    m = len(names)
    if isinstance(hierarchy, Mapping):
        parent = np.full(m, -1)
        explicit_roots = []
        for child, par in hierarchy.items():
            i = _index(child, names, "hierarchy")
            if par is None or par == "":
                explicit_roots.append(names[i])
                continue
            p = _index(par, names, "hierarchy")
            if p == i:
                raise SolverError(f"hierarchy: {names[i]!r} is given as its own parent")
            parent[i] = p
        if len(explicit_roots) > 1:
            raise SolverError(f"hierarchy: the root is given twice ({', '.join(explicit_roots)}); a skeleton has one root")
    else:
        parent = np.asarray(hierarchy)
        if parent.shape != (m,) or not np.issubdtype(parent.dtype, np.integer):
            raise SolverError(f"hierarchy: a parent array must hold {m} integers, got {parent.shape} {parent.dtype}")
        parent = parent.astype(int)
        if ((parent < -1) | (parent >= m)).any() or (parent == np.arange(m)).any():
            raise SolverError("hierarchy: parent indices must be −1 (root) or another sensor's index")
    roots = np.flatnonzero(parent < 0)
    # Walk up from every sensor at once; after m steps only sensors on a cycle have not reached a root.
    up = parent.copy()
    for _ in range(m):
        up = np.where(up >= 0, parent[np.maximum(up, 0)], up)
    cyc = np.flatnonzero(up >= 0)
    if len(cyc):
        raise SolverError(f"hierarchy: {', '.join(names[i] for i in cyc)} form a cycle; a skeleton must be a tree")
    if len(roots) > 1:
        raise SolverError(
            f"hierarchy: {len(roots)} sensors have no parent ({', '.join(names[i] for i in roots)}); "
            "give every sensor but the root a parent"
        )
    return parent


def calibrate(acc, hierarchy=None, root=None, names=None) -> Calibration:
    """Fit the skeleton from accumulator `acc`: the given `hierarchy` ({child: parent}) or a searched tree.

    `root` (name or index) hangs a searched tree from that sensor; with a hierarchy it must be its root.
    With a hierarchy only its m − 1 joints are solved (the paper's fast path).
    """
    m = acc.n_sensors
    names = tuple(str(x) for x in (names if names is not None else range(m)))
    if len(names) != m:
        raise SolverError(f"{len(names)} names given for {m} sensors")
    root_i = None if root is None else _index(root, names, "root")
    if hierarchy is not None:
        parent = parse_hierarchy(hierarchy, names)
        hroot = int(np.flatnonzero(parent < 0)[0])
        if root_i is not None and root_i != hroot:
            raise SolverError(f"root {names[root_i]!r} disagrees with the hierarchy, whose root is {names[hroot]!r}")
        kids = np.flatnonzero(parent >= 0)
        _, order = _orient(np.stack([kids, parent[kids]], axis=1), m, hroot)
        jc = order[1:]
        joints = pair_fits(acc, np.stack([jc, parent[jc]], axis=1))
        flat = joints.rank <= 3
        rigid_groups = []
        if flat.any():
            e = joints.pairs[flat]
            n_g, lab = connected_components(csr_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(m, m)), directed=False)
            rigid_groups = [list(map(int, np.flatnonzero(lab == g))) for g in range(n_g) if (lab == g).sum() > 1]
        cal = Calibration(names, hroot, parent, order, acc.frames, joints, _no_bones(), np.full((m, 3), np.nan),
                          rigid_groups=rigid_groups, hierarchy_given=True)
    else:
        fits = pair_fits(acc)
        topo = spanning_tree(fits, m, root_i)
        jc = topo.order[topo.joint[topo.order]]
        pj = topo.parent[jc]
        lo, hi = np.minimum(jc, pj), np.maximum(jc, pj)
        row = lo * m - lo * (lo + 1) // 2 + (hi - lo - 1)  # index of (lo, hi) in all_pairs order
        joints = fits.take(row, swap=jc > pj)
        cal = Calibration(names, topo.root, topo.parent, topo.order, acc.frames, joints, _no_bones(),
                          np.full((m, 3), np.nan), topo.loop_candidates, topo.rigid_groups, topo.ambiguous, fits)
    cal.placement = _placement(acc, cal)
    cal.bones = _bones(acc, cal)
    return cal


def _no_bones() -> Bones:
    z = np.zeros(0)
    return Bones(z.astype(int), z.astype(int), z.astype(int), z, z, z.astype(bool))


def _placement(acc, cal: Calibration) -> np.ndarray:
    m = cal.n_sensors
    place = np.full((m, 3), np.nan)
    jc = cal.joint_child
    place[jc] = cal.c
    is_joint = np.zeros(m, dtype=bool)
    is_joint[jc] = True
    members = np.flatnonzero(~is_joint & (cal.parent >= 0))  # rigidly attached to their group's joint member
    if len(members):
        ent = cal.parent[members]
        place[members] = acc.pair_point(place[ent], ent, members)
    return place


def _bones(acc, cal: Calibration) -> Bones:
    """Inboard → each outboard joint per body, and between outboard joints at the root (design.md §5)."""
    m = cal.n_sensors
    J = cal.joints
    jc, jp = J.pairs[:, 0], J.pairs[:, 1]
    is_joint = np.zeros(m, dtype=bool)
    is_joint[jc] = True
    # The body an outboard joint hangs from, named by its entry sensor (a rigid member defers to its entry).
    body = np.where(is_joint[jp] | (jp == cal.root), jp, cal.parent[jp])
    moved = body != jp
    pt = J.l.copy()
    cov = J.l_cov.copy()
    if moved.any():
        pt[moved] = acc.pair_point(J.l[moved], jp[moved], body[moved])
        Q = acc.relative_rotation(jp[moved], body[moved])
        cov[moved] = Q @ J.l_cov[moved] @ Q.transpose(0, 2, 1)
    row = {int(c): k for k, c in enumerate(jc)}
    out_body, out_from, out_to, length, stderr, at_root = [], [], [], [], [], []

    def add(bd, a, b, pa, pb, ca, cb, rooted):
        d = pa - pb
        L = float(np.linalg.norm(d))
        g = d / L if L > 0 else np.zeros(3)
        out_body.append(bd), out_from.append(a), out_to.append(b), at_root.append(rooted)
        length.append(L)
        stderr.append(float(np.sqrt(max(g @ (ca + cb) @ g, 0.0))))

    for bd in np.unique(body):  # one pass per body (≤ m)
        outs = np.flatnonzero(body == bd)
        if bd in row:  # the body has an inboard joint: c of that joint, in bd's frame
            k = row[int(bd)]
            for o in outs:
                add(int(bd), int(bd), int(jc[o]), J.c[k], pt[o], J.c_cov[k], cov[o], False)
        else:
            for x, a in enumerate(outs):
                for b in outs[x + 1:]:
                    add(int(bd), int(jc[a]), int(jc[b]), pt[a], pt[b], cov[a], cov[b], True)
    return Bones(np.array(out_body, dtype=int), np.array(out_from, dtype=int), np.array(out_to, dtype=int),
                 np.array(length, dtype=float), np.array(stderr, dtype=float), np.array(at_root, dtype=bool))
