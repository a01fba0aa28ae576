"""Residual removal (paper §3.4): play a take back through the fitted articulated model.

Only the sensors' rotations and the root's translation drive the model, so joints cannot separate;
the raw data's joint separations (the residuals) are what this removes. Pure numpy, no I/O.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from flockcal.errors import FlockcalError
from flockcal.solver.hierarchy import check_tree


class ArticulationError(FlockcalError, ValueError):
    """A calibration that cannot drive a take (names that do not match, a parent map that is no tree)."""


@dataclass(frozen=True)
class Articulation:
    """A rooted tree of rigid bodies, one sensor each, with every joint located in both bodies' frames.

    `c[j]` is body j's inboard joint in j's sensor frame, `l[j]` the same point in its parent's frame
    (both zero at the root, which has no inboard joint). `order` lists the root first and every
    parent before its children.
    """

    names: tuple[str, ...]
    parent: np.ndarray  # (m,) int, -1 at the root
    c: np.ndarray  # (m, 3) metres
    l: np.ndarray  # (m, 3) metres
    order: np.ndarray  # (m,) int
    rigid: np.ndarray | None = None  # (m,) bool: rigidly attached to its parent, no joint fitted (c = 0, l NaN until completed)

    @property
    def root(self) -> int:
        return int(self.order[0])

    @property
    def n_bodies(self) -> int:
        return len(self.names)

    @cached_property
    def levels(self) -> tuple[np.ndarray, ...]:
        """Bodies grouped by depth below the root (the root alone first): a tree walk can place a whole
        level at once, since every body's parent lies in the level before it."""
        depth = np.zeros(self.n_bodies, dtype=int)
        for j in self.order[1:]:
            depth[j] = depth[self.parent[j]] + 1
        return tuple(np.flatnonzero(depth == d) for d in range(depth.max() + 1))

    def children(self, i: int) -> list[int]:
        return [int(j) for j in np.flatnonzero(self.parent == i)]

    def origin(self) -> np.ndarray:
        """(m, 3) each body's pivot in its own sensor frame: its inboard joint, the sensor at the root."""
        return self.c.copy()

    def reordered(self, names: Sequence[str]) -> "Articulation":
        """The same tree with bodies indexed as in `names` (a take's sensor order); the names must match."""
        names = tuple(str(x) for x in names)
        missing = [x for x in self.names if x not in names]
        extra = [x for x in names if x not in self.names]
        if missing or extra:
            parts = []
            if missing:
                parts.append(f"the calibration has sensor(s) {', '.join(missing)} that the take lacks")
            if extra:
                parts.append(f"the take has sensor(s) {', '.join(extra)} that the calibration lacks")
            raise ArticulationError(
                "; ".join(parts) + " — use a calibration made for this sensor set (same sensor names)"
            )
        if names == self.names:
            return self
        perm = np.array([self.names.index(x) for x in names])  # new index -> old index
        inverse = np.empty_like(perm)
        inverse[perm] = np.arange(len(perm))
        old_parent = self.parent[perm]
        parent = np.where(old_parent < 0, -1, inverse[np.maximum(old_parent, 0)])
        rigid = None if self.rigid is None else self.rigid[perm]
        return Articulation(names, parent, self.c[perm], self.l[perm], inverse[self.order], rigid)

    def joint_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(child→parent index pairs (m−1, 2), c (m−1, 3), l (m−1, 3)) of the tree's joints, as
        `Calibration.joint_arrays` gives them (what solver/humanoid.py's helpers read)."""
        child = np.flatnonzero(self.parent >= 0)
        return np.stack([child, self.parent[child]], axis=1), self.c[child], self.l[child]

    def rerooted(self, root: int) -> "Articulation":
        """The same joints hung from body `root`: every joint on the path from the old root to it turns
        round (its c and l swap, as do child and parent); a body riding rigidly on its parent leaves its
        parent riding rigidly on it. Complete the articulation first (a rigid body's l must be known)."""
        root = int(root)
        if root == self.root:
            return self
        parent, c, l = self.parent.copy(), self.c.copy(), self.l.copy()
        rigid = None if self.rigid is None else self.rigid.copy()
        below = root
        while self.parent[below] >= 0:  # walk up the old tree, turning each joint on the way
            above = int(self.parent[below])
            parent[above], c[above], l[above] = below, self.l[below], self.c[below]
            if rigid is not None:
                rigid[above] = self.rigid[below]
            below = above
        parent[root] = -1
        c[root] = l[root] = 0.0
        if rigid is not None:
            rigid[root] = False
        return Articulation(self.names, parent, c, l, tree_order(parent), rigid)

    @property
    def incomplete(self) -> np.ndarray:
        """(m,) bool: rigidly attached bodies whose offset from the parent is not yet known."""
        if self.rigid is None:
            return np.zeros(self.n_bodies, dtype=bool)
        return self.rigid & ~np.isfinite(self.l).all(axis=1)

    def completed(self, rotations=None, positions=None, valid=None, acc=None, frames=None) -> "Articulation":
        """Rigidly attached bodies given a joint at their own sensor: l = that sensor's mean position in
        the parent's frame, from a take's frames (arrays, or `frames`: an iterable of `flockcal.frames.Frames`
        chunks, summed a chunk at a time) or from a GramAccumulator (`acc.pair_point`)."""
        todo = np.flatnonzero(self.incomplete)
        if not len(todo):
            return self
        l = self.l.copy()
        p = self.parent[todo]
        if acc is not None:
            l[todo] = acc.pair_point(np.zeros((len(todo), 3)), todo, p)
        elif frames is not None:
            l[todo] = _rigid_means(((f.rotations, f.positions, f.valid) for f in frames), todo, p)
        elif rotations is not None and positions is not None:
            l[todo] = _rigid_means([(rotations, positions, valid)], todo, p)
        else:
            raise ArticulationError("completing rigidly attached sensors needs the take's frames or its accumulator")
        if not np.isfinite(l[todo]).all():
            lacking = [self.names[i] for i in todo[~np.isfinite(l[todo]).all(axis=1)]]
            raise ArticulationError(f"no frame has sensor(s) {', '.join(lacking)} and their parent both valid")
        done = Articulation(self.names, self.parent, self.c, l, self.order, self.rigid)
        if "levels" in self.__dict__:  # same tree: keep the cached walk (live poses complete every frame)
            done.__dict__["levels"] = self.levels
        return done


def _rigid_means(chunks, j: np.ndarray, p: np.ndarray) -> np.ndarray:
    """(k, 3) mean of R_pᵀ (t_j − t_p) over the frames where both sensors are valid (and the value is a
    number), summed chunk by chunk of (rotations, positions, valid|None): one chunk gives np.nanmean's bits."""
    total = count = None
    for R, t, valid in chunks:
        R = np.asarray(R, dtype=float)
        t = np.asarray(t, dtype=float)
        rel = np.einsum("nkba,nkb->nka", R[:, p], t[:, j] - t[:, p])  # R_pᵀ (t_j − t_p)
        ok = ~np.isnan(rel)
        if valid is not None:
            v = np.asarray(valid, dtype=bool)
            ok &= (v[:, j] & v[:, p])[..., None]
        part, n = np.where(ok, rel, 0.0).sum(axis=0), ok.sum(axis=0)
        total, count = (part, n) if total is None else (total + part, count + n)
    if total is None:
        return np.full((len(j), 3), np.nan)
    with np.errstate(invalid="ignore", divide="ignore"):
        return total / count


def tree_order(parent: np.ndarray) -> np.ndarray:
    """Root first, parents before children; raises ArticulationError unless `parent` is one rooted tree
    (solver/hierarchy.py's `check_tree`, the one check of a tree)."""
    parent = np.asarray(parent, dtype=int)
    order = [check_tree(parent, what="the parent map", error=ArticulationError)]
    k = 0
    while k < len(order):
        order += np.flatnonzero(parent == order[k]).tolist()
        k += 1
    return np.asarray(order)


def articulation(calibration) -> Articulation:
    """An Articulation from a Calibration (or a fit with `.calibration()`), or from a docs/design.md §5 dict
    (fit JSON or a skeleton file, read by `calibration_from_json`: only `sensors`, `root`, `parent`,
    `joints[].child/parent/c/l` and `rigid_groups`, the stable contract)."""
    from flockcal.solver.calibration_json import as_calibration

    cal = as_calibration(calibration, error=ArticulationError)
    names = tuple(cal.names)
    m = len(names)
    parent = np.asarray(cal.parent, dtype=int)
    order = tree_order(parent)
    pairs, jc, jl = cal.joint_arrays()
    tree = parent[pairs[:, 0]] == pairs[:, 1]  # a non-tree joint (loop candidate) takes no part
    c = np.zeros((m, 3))
    l = np.zeros((m, 3))
    have = np.zeros(m, dtype=bool)
    c[pairs[tree, 0]] = jc[tree]
    l[pairs[tree, 0]] = jl[tree]
    have[pairs[tree, 0]] = True
    # A sensor that never turned against its parent has no joint (its centre is undetermined): it rides
    # rigidly on the parent, completed later from the frames (`Articulation.completed`).
    group = {}
    for g, members in enumerate(cal.rigid_groups or []):
        for x in members:
            group[names[x]] = g
    rigid = np.zeros(m, dtype=bool)
    lacking = []
    for i in range(m):
        if parent[i] < 0 or have[i]:
            continue
        if names[i] in group and group[names[i]] == group.get(names[parent[i]], -1):
            rigid[i] = True
            l[i] = np.nan
        else:
            lacking.append(names[i])
    if lacking:
        raise ArticulationError(f"no joint given for sensor(s) {', '.join(lacking)} of the tree")
    bad = ~(np.isfinite(c).all(axis=1) & (np.isfinite(l).all(axis=1) | rigid))
    if bad.any():
        raise ArticulationError(
            f"joint(s) of {', '.join(names[i] for i in np.flatnonzero(bad))} have no centre (null or NaN): "
            "the take has no frames where both sensors were valid — record more, or leave those sensors out"
        )
    return Articulation(names, parent, c, l, order, rigid if rigid.any() else None)


def held_poses(rotations: np.ndarray, positions: np.ndarray, valid: np.ndarray | None = None, missing: str = "raise",
               before: tuple[np.ndarray, np.ndarray] | None = None):
    """Rotations and positions with every invalid sensor-frame replaced by that sensor's last valid one.

    Frames before a sensor's first valid record take its first valid one, or with `before` ((m, 3, 3),
    (m, 3): the pose each sensor held before these frames, a chunk's carry) that one. A sensor that is never
    valid has nothing to hold: ArticulationError, or NaN throughout with `missing="nan"` (a live single frame).
    """
    R = np.asarray(rotations, dtype=float)
    t = np.asarray(positions, dtype=float)
    if valid is None:
        return R, t
    valid = np.asarray(valid, dtype=bool)
    if valid.all():
        return R, t
    n, m = valid.shape
    frame = np.arange(n)[:, None]
    last = np.maximum.accumulate(np.where(valid, frame, -1), axis=0)
    cols = np.broadcast_to(np.arange(m), (n, m))
    if before is not None:
        R, t = R[np.maximum(last, 0), cols], t[np.maximum(last, 0), cols]
        lead = last < 0
        R[lead] = np.broadcast_to(before[0], (n, m, 3, 3))[lead]
        t[lead] = np.broadcast_to(before[1], (n, m, 3))[lead]
        return R, t
    never = np.flatnonzero(~valid.any(axis=0))
    if len(never) and missing != "nan":
        raise ArticulationError(f"sensor index(es) {never.tolist()} never gave a valid record; nothing to play back")
    first = valid.argmax(axis=0)
    source = np.where(last < 0, first[None, :], last)  # (n, m) frame index to read from
    R, t = R[source, cols], t[source, cols]
    if len(never):
        R[:, never] = np.nan
        t[:, never] = np.nan
    return R, t


def first_valid(frames) -> tuple[np.ndarray, np.ndarray]:
    """((m, 3, 3), (m, 3)): each sensor's first valid pose in `frames` (an iterable of `Frames` chunks, read
    until every sensor has one): what a take holds before a sensor's first record."""
    R0 = t0 = todo = None
    for f in frames:
        if R0 is None:
            m = f.rotations.shape[1]
            R0, t0, todo = np.full((m, 3, 3), np.nan), np.full((m, 3), np.nan), np.ones(m, dtype=bool)
        found = todo & f.valid.any(axis=0)
        if found.any():
            k = f.valid.argmax(axis=0)
            cols = np.flatnonzero(found)
            R0[cols], t0[cols] = f.rotations[k[cols], cols], f.positions[k[cols], cols]
            todo &= ~found
        if not todo.any():
            break
    if todo is None or todo.any():
        never = [] if todo is None else np.flatnonzero(todo).tolist()
        raise ArticulationError(f"sensor index(es) {never} never gave a valid record; nothing to play back")
    return R0, t0


def tree_residuals(rotations, positions, art: Articulation, valid=None) -> np.ndarray:
    """(n, m, 3) e_k = R_j c_j + t_j − R_p l_j − t_p (world metres) for each tree joint, indexed by child.

    NaN at the root and where either sensor of the joint is invalid.
    """
    R = np.asarray(rotations, dtype=float)
    t = np.asarray(positions, dtype=float)
    par = np.maximum(art.parent, 0)
    e = np.einsum("nmab,mb->nma", R, art.c) + t - np.einsum("nmab,mb->nma", R[:, par], art.l) - t[:, par]
    e[:, art.parent < 0] = np.nan
    if valid is not None:
        valid = np.asarray(valid, dtype=bool)
        e[~(valid & valid[:, par])] = np.nan
    return e


def joint_separation(rotations, positions, art: Articulation, valid=None) -> np.ndarray:
    """(n, m) world distance between the two bodies' copies of each tree joint (indexed by its child).

    This is ‖e_k‖ of docs/design.md §1 for the tree joints; NaN at the root and where either sensor is invalid.
    """
    return np.linalg.norm(tree_residuals(rotations, positions, art, valid), axis=-1)


@dataclass(frozen=True)
class Reconstruction:
    """A take played back through an articulated model (arrays over n frames, m bodies, world metres)."""

    rotations: np.ndarray  # (n, m, 3, 3) body -> world; invalid frames hold the last valid rotation
    sensor_positions: np.ndarray  # (n, m, 3) where the model puts each sensor
    joint_positions: np.ndarray  # (n, m, 3) each body's pivot: inboard joint, root sensor at the root
    articulation: Articulation

    def separation(self) -> np.ndarray:
        """(n, m) joint separation of the reconstruction: zero up to rounding, NaN at the root."""
        return joint_separation(self.rotations, self.sensor_positions, self.articulation)


def reconstruct(rotations, positions, art: Articulation, valid=None, missing: str = "raise") -> Reconstruction:
    """Drive `art` by the take's rotations and its root sensor's translation (paper §3.4).

    Each body's sensor is placed so its inboard joint coincides with the parent's copy of that joint:
    t'_j = R_p l_j + t'_p − R_j c_j, walking the tree from the root (one vectorised step per body).
    A sensor with no valid frame at all raises ArticulationError, or with `missing="nan"` leaves NaN in
    its subtree (for a live single frame where a bird dropped out).
    """
    if art.incomplete.any():
        art = art.completed(rotations, positions, valid)
    R, t = held_poses(rotations, positions, valid, missing)
    if R.ndim != 4 or R.shape[1] != art.n_bodies:
        raise ArticulationError(f"take has {R.shape[1] if R.ndim == 4 else '?'} sensors, the model {art.n_bodies}")
    sensor = np.empty_like(t)
    root = art.root
    sensor[:, root] = t[:, root]
    for level in art.levels[1:]:  # a level at a time: a human's 16 bodies take 5 steps, not 15
        p = art.parent[level]
        sensor[:, level] = (np.einsum("nkab,kb->nka", R[:, p], art.l[level]) + sensor[:, p]
                            - np.einsum("nkab,kb->nka", R[:, level], art.c[level]))
    joints = np.einsum("nmab,mb->nma", R, art.c) + sensor
    return Reconstruction(R, sensor, joints, art)


def reconstruct_chunks(frames, art: Articulation, before: tuple[np.ndarray, np.ndarray]) -> Iterator[Reconstruction]:
    """`reconstruct` of a take a chunk at a time (`frames`: an iterable of `Frames`; `art` complete), each
    invalid sensor-frame holding the sensor's last valid pose, carried from chunk to chunk from `before`
    (`first_valid`: what a whole take holds before a sensor's first record)."""
    for f in frames:
        R, t = held_poses(f.rotations, f.positions, f.valid, before=before)
        if len(R):
            before = (R[-1], t[-1])
        yield reconstruct(R, t, art)
