"""A whole-skeleton calibration from one accumulator: topology (searched or given), tree joints, bones, placement.

`calibrate` is what `flockcal fit` and the live server call (≥30×/s): all-pair fits, MST and the tree's
joints are array operations; `Calibration` is the solver's one result type, whose `to_dict()` is the
JSON of docs/design.md §5 (built in solver/calibration_json.py).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np

from flockcal.solver.errors import SolverError
from flockcal.solver.fits import TOLERANCE_M, PairFits, pair_fits
from flockcal.solver.hierarchy import parse_hierarchy, sensor_index
from flockcal.solver.hinge_point import hinge_offsets
from flockcal.solver.topology import orient, rigid_bodies, spanning_tree

if TYPE_CHECKING:
    from flockcal.solver.humanoid import Humanoid


@dataclass(frozen=True)
class Bones:
    """Distances between two joint centres of one body, in that body's frame (docs/design.md §5)."""

    body: np.ndarray  # (B,) sensor index of the body (for a rigid group: the member holding its inboard joint)
    from_joint: np.ndarray  # (B,) child index of the inboard joint, or of the first outboard joint at the root
    to_joint: np.ndarray  # (B,) child index of the outboard joint
    length: np.ndarray  # (B,) m
    stderr: np.ndarray  # (B,) m
    at_root: np.ndarray  # (B,) bool: between two outboard joints of the root body (no inboard joint)
    segment_start_s: np.ndarray | None = None  # (B,) s: refitted on the frames since a slip; NaN: whole take

    def __len__(self) -> int:
        return len(self.body)


@dataclass(frozen=True)
class OpticalExtras:
    """What an optical-marker fit adds to the calibration (its §5 JSON's extra keys)."""

    kirk_rms: np.ndarray  # (J,) m, per joint: the Kirk fit's rms on the marker data
    bodies: Mapping  # {body label: [marker names]}
    markers: Mapping  # {marker: {"body": label, "offset": [x, y, z] or None}}
    unused_markers: tuple
    swap_events: tuple  # ({"time_s", "stop_s", "markers", "bodies"}, …)
    marker_outlier_threshold_m: float
    joint_decisions: tuple = ()  # per joint: {"determined", "direction_error_m"} judged from the bodies' poses
    exercise: Mapping = field(default_factory=dict)  # what the take exercised: exercised_joints, unjoined, …


@dataclass(frozen=True, eq=False)
class Calibration:
    """The solver's one result: a whole-skeleton fit, whichever way it was made (searched or given tree,
    after slips, a saved skeleton, optical markers). Arrays inside, SI units; `to_dict()` is its §5 JSON.

    Joint arrays are in tree order (`order[1:]`); `segment_start_s` marks joints refitted after a slip,
    `rms_free` the free fit of each joint under a saved skeleton (`known_skeleton`), `optical` what a
    marker fit adds, `humanoid` which humanoid bone each body is (found from a sample of the take's frames,
    `solve(..., sample=)`). Build variants with `dataclasses.replace`; nothing here is changed in place.

    Made by `flockcal.fit` (a take) and `calibrate` / `solve` (an accumulator), never by hand. m sensors,
    J tree joints; a joint is a (child, parent) pair of sensor indices, `c` in the child's frame and `l` in
    the parent's, metres.

    Attributes
    ----------
    names : tuple of str
        The m sensor names, in the take's order.
    root : int
        The sensor the tree hangs from.
    parent : ndarray of int, shape (m,)
        Each sensor's parent in the tree, -1 at the root.
    order : ndarray of int, shape (m,)
        The sensors root first, every parent before its children.
    frames : int
        Frames the fit summed.
    joints : flockcal.solver.fits.PairFits
        The tree's joints, in `order` (``order[1:]``): ``pairs`` (J, 2), centres ``c`` and ``l`` (J, 3),
        ``rms`` (J,) residual, ``hinge`` and its axes, ``coverage``, standard errors, ``determined``
        (J,) bool: the data pin the centre to the tolerance (docs/design.md §3a). Shortcuts on the
        calibration itself: `c`, `l`, `rms`, `hinge`, `determined`, … .
    bones : Bones
        Joint-to-joint distances within each body, metres, with their standard errors.
    placement : ndarray, shape (m, 3)
        Each sensor's offset from its inboard joint in its own frame (NaN at the root).
    loop_candidates, rigid_groups, ambiguous : list
        Pairs outside the tree that fit like joints; groups of sensors that never turned against each
        other; children whose parent the data cannot tell.
    fits : flockcal.solver.fits.PairFits or None
        Every pair's fit, when the tree was searched.
    hierarchy_given : bool
        The tree was given, not searched.
    slip_events : tuple
        The slips and swaps (`flockcal.solver.SlipEvent`, `flockcal.solver.SwapEvent`) the fit was
        segmented at.
    segment_start_s : ndarray, shape (J,), or None
        Seconds: a joint re-fitted on the frames since a slip; NaN where it holds the whole take.
    humanoid : flockcal.solver.Humanoid or None
        Which humanoid bone each body is (`joint_names()` names the joints by it); None where it was not
        looked for.

    See Also
    --------
    flockcal.fit : fit a take.

    Examples
    --------
    >>> import flockcal
    >>> take, _ = flockcal.simulate(motion="exercise", seconds=20, birds=4, seed=1)
    >>> cal = flockcal.fit(take, root="pelvis")
    >>> cal.names[cal.root], cal.parent_map()
    ('pelvis', {'chest': 'pelvis', 'head': 'chest', 'l_upper_arm': 'chest'})
    >>> cal.c.shape, bool(cal.determined.all())
    ((3, 3), True)
    >>> cal.to_dict()["root"]          # the object `flockcal fit --json` prints
    'pelvis'
    """

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
    slip_events: tuple = ()  # SlipEvent/SwapEvent (or their JSON objects) the fit was segmented at
    segment_start_s: np.ndarray | None = None  # (J,) s: joint refitted on the frames since a slip; NaN: whole take
    known_skeleton: bool = False  # topology and bones from a saved skeleton, only placements fitted
    rms_free: np.ndarray | None = None  # (J,) m: each joint fitted freely (saved-skeleton fits)
    optical: OpticalExtras | None = None
    state: object = None  # what the next refresh starts from (a saved-skeleton fit's KnownFit); not in the JSON
    hinge_point: "HingePoints | None" = None  # how each hinge's centre was placed on its axis
    humanoid: "Humanoid | None" = None  # which humanoid bone each body is (solver/humanoid.py); None: not looked for

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
    determined = property(lambda self: self.joints.determined)
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

    def joint_names(self) -> list[str]:
        """Each tree joint's name as people say it, in joint order: the humanoid's ("left knee", "lower
        back") on a human tree, else the sensor names' reading (flockcal/names.py: "left elbow", "bird 1–bird 2")."""
        from flockcal.names import joint_name

        nm, hum = self.names, self.humanoid
        out = []
        for c, p in self.joints.pairs.tolist():
            name = hum.joint_name(c, p) if hum is not None and hum.human else None
            out.append(name or joint_name(nm[c], nm[p]))
        return out

    def joint_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(child→parent index pairs (J, 2), c (J, 3), l (J, 3)): what pose and slip code read."""
        return self.joints.pairs, self.joints.c, self.joints.l

    def to_dict(self, slip_events=None) -> dict:
        """The `flockcal fit --json` object of docs/design.md §5 (see `calibration_json`); `slip_events`, when
        given, replaces the calibration's own."""
        from flockcal.solver.calibration_json import calibration_json

        cal = self if slip_events is None else replace(self, slip_events=tuple(slip_events))
        return calibration_json(cal)


def calibrate(acc, hierarchy=None, root=None, names=None, tolerance: float = TOLERANCE_M,
              fits: PairFits | None = None) -> Calibration:
    """Fit the skeleton from accumulator `acc`: the given `hierarchy` ({child: parent}) or a searched tree.

    `root` (name or index) hangs a searched tree from that sensor; with a hierarchy it must be its root.
    `fits`: the fits of all pairs to search the tree on, if not `pair_fits(acc)` (a segmented take's, whose
    slipped pairs are judged on each placement's own fit: solver/segments.py).
    With a hierarchy only its m − 1 joints are solved (the paper's fast path). `tolerance` (m): how closely
    a joint's centre must be pinned to count as determined (docs/design.md §3a); only determined joints end bones.
    """
    m = acc.n_sensors
    names = tuple(str(x) for x in (names if names is not None else range(m)))
    if len(names) != m:
        raise SolverError(f"{len(names)} names given for {m} sensors")
    root_i = None if root is None else sensor_index(root, names, "root")
    if hierarchy is not None:
        parent = parse_hierarchy(hierarchy, names, root)
        hroot = int(np.flatnonzero(parent < 0)[0])
        kids = np.flatnonzero(parent >= 0)
        _, order = orient(np.stack([kids, parent[kids]], axis=1), m, hroot)
        jc = order[1:]
        joints = pair_fits(acc, np.stack([jc, parent[jc]], axis=1), tolerance=tolerance)
        flat = joints.rank <= 3
        rigid_groups = []
        if flat.any():
            e = joints.pairs[flat]
            rigid = np.zeros((m, m), dtype=bool)
            rigid[e[:, 0], e[:, 1]] = True
            n_g, lab = rigid_bodies(rigid.tobytes(), m)  # memoised: the same joints stay rigid refit after refit
            groups: list[list[int]] = [[] for _ in range(n_g)]
            for i, g in enumerate(lab.tolist()):
                groups[g].append(i)
            rigid_groups = [g for g in groups if len(g) > 1]
        cal = Calibration(names, hroot, parent, order, acc.frames, joints, _no_bones(), np.full((m, 3), np.nan),
                          rigid_groups=rigid_groups, hierarchy_given=True)
    else:
        if fits is None:
            fits = pair_fits(acc, tolerance=tolerance)
        topo = spanning_tree(fits, m, root_i)
        jc = topo.order[topo.joint[topo.order]]
        pj = topo.parent[jc]
        lo, hi = np.minimum(jc, pj), np.maximum(jc, pj)
        row = lo * m - lo * (lo + 1) // 2 + (hi - lo - 1)  # index of (lo, hi) in all_pairs order
        joints = fits.take(row, swap=jc > pj)
        cal = Calibration(names, topo.root, topo.parent, topo.order, acc.frames, joints, _no_bones(),
                          np.full((m, 3), np.nan), topo.loop_candidates, topo.rigid_groups, topo.ambiguous,
                          fits)
    joints, how = placed_hinges(acc, cal.joints, tolerance)
    cal = replace(cal, joints=joints, hinge_point=how)
    cal = replace(cal, placement=_placement(acc, cal))
    return replace(cal, bones=joint_bones(acc, cal))


@dataclass(frozen=True)
class HingePoints:
    """How each tree joint's centre was placed on its hinge axis (solver/hinge_point.py)."""

    rule: np.ndarray  # (J,) 2 or 1: where the limb's bones meet the axis (bones used); 3: a bone and the next
    # hinge's axis; 0: min-norm; −1: not a hinge
    data_share: np.ndarray  # (J,) the share of the least-squares point in it (0: none)

    def take(self, index) -> "HingePoints":
        return HingePoints(self.rule[index], self.data_share[index])


def placed_hinges(acc, joints: PairFits, tolerance: float = TOLERANCE_M) -> tuple[PairFits, HingePoints]:
    """The tree's `joints` with each hinge's centre slid along its axis to the rule's point
    (solver/hinge_point.py; `tolerance`: the fit's, which says which neighbours' centres count), its
    residual recomputed there; and how each was placed."""
    s, how, share = hinge_offsets(joints.pairs, joints.c, joints.l, joints.axis_i, joints.axis_j, joints.hinge,
                                  joints.determined, joints.axis_offset, joints.direction_error[:, 0],
                                  joints.direction_error.max(axis=1), tolerance)
    moved = np.flatnonzero((how >= 0) & (s != 0))
    how = HingePoints(how, share)
    if not len(moved):
        return joints, how
    c, l = joints.c.copy(), joints.l.copy()
    c[moved] += s[moved, None] * joints.axis_i[moved]
    l[moved] += s[moved, None] * joints.axis_j[moved]
    # The residual at the new point: SSE(u) = uᵀAu − 2bᵀu + Σ‖d‖². Along the axis it grows by n μ₀ s²
    # at most, μ₀ being the rotation about the axis's own direction that the data barely saw.
    A, b, dd, n = acc.normal_equations(joints.pairs[moved])
    u = np.concatenate([c[moved], l[moved]], axis=1)
    sse = np.maximum(np.einsum("pi,pij,pj->p", u, A, u) - 2.0 * (b * u).sum(axis=1) + dd, 0.0)
    nn = np.maximum(n, 1.0)
    rms, eps = joints.rms.copy(), joints.epsilon.copy()
    rms[moved], eps[moved] = np.sqrt(sse / nn), np.sqrt(sse) / nn
    return replace(joints, c=c, l=l, rms=rms, epsilon=eps), how


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


def joint_bones(acc, cal: Calibration) -> Bones:
    """Inboard → each outboard joint per body, and between outboard joints at the root (docs/design.md §5),
    measured between `cal.joints`' centres; `acc` places a joint hung from a rigidly attached sensor."""
    m = cal.n_sensors
    J = cal.joints
    jc, jp = J.pairs[:, 0], J.pairs[:, 1]
    is_joint = np.zeros(m, dtype=bool)
    is_joint[jc] = True
    # The body an outboard joint hangs from, named by its entry sensor (a rigid member defers to its entry).
    body = np.where(is_joint[jp] | (jp == cal.root), jp, cal.parent[jp])
    moved = body != jp
    pt, cov = J.l, J.l_cov
    if moved.any():
        pt, cov = pt.copy(), cov.copy()
        pt[moved] = acc.pair_point(J.l[moved], jp[moved], body[moved])
        Q = acc.relative_rotation(jp[moved], body[moved])
        cov[moved] = Q @ J.l_cov[moved] @ Q.transpose(0, 2, 1)

    # Every bone at once. A body with an inboard joint (row k_in) has a bone from that joint's c to each
    # outboard joint o; a body without one (the root) has one between every two outboard joints a < b.
    # A bone's first end indexes [c of every joint; outboard points], its second end the outboard points.
    row_of = np.full(m, -1)
    row_of[jc] = np.arange(len(jc))
    k_in = row_of[body]
    o = np.flatnonzero(k_in >= 0)
    rows = np.arange(len(jc))
    a, b = np.nonzero((body[:, None] == body[None, :]) & (k_in < 0)[:, None] & (rows[:, None] < rows[None, :]))
    first = np.concatenate([k_in[o], len(jc) + a])
    second = np.concatenate([o, b])
    from_joint = np.concatenate([body[o], jc[a]])
    by_body = np.argsort(body[second], kind="stable")  # bodies ascending, each in the joint order above
    first, second, from_joint = first[by_body], second[by_body], from_joint[by_body]

    # Only determined joints end a bone: an undetermined centre is a rule's point, not a measurement.
    det = np.asarray(J.determined, dtype=bool)
    ok = np.concatenate([det, det])[first] & det[second]
    first, second, from_joint = first[ok], second[ok], from_joint[ok]

    d = np.concatenate([J.c, pt])[first] - pt[second]
    length = np.sqrt((d[:, None, :] @ d[:, :, None])[:, 0, 0])  # a dot product, as np.linalg.norm takes it
    pos = length > 0
    g = np.where(pos[:, None], d / np.where(pos, length, 1.0)[:, None], 0.0)
    C = np.concatenate([J.c_cov, cov])[first] + cov[second]
    var = (g[:, None, :] @ C @ g[:, :, None])[:, 0, 0]  # the length's variance, along the bone
    return Bones(body[second], from_joint, jc[second], length, np.sqrt(np.maximum(var, 0.0)), first >= len(jc))
