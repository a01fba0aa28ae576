"""Fit a take with a saved skeleton (`Skeleton`): topology and bone lengths fixed, only sensor placements move.

Each body's saved joint points are moved as one rigid piece into the new take's sensor frame: a
Procrustes start from the free per-joint fits, then Gauss–Newton on the exact least-squares cost of all
tree joints (read from the Gram normal equations), so bones stay the saved ones to rounding.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from flockcal.rotations import skew
from flockcal.skeleton import SkeletonError
from flockcal.solver.calibration import Bones, Calibration
from flockcal.solver.calibration_json import bones_json
from flockcal.solver.fits import PairFits, unfitted
from flockcal.solver.hinge_point import LIMB_RULE_SD_M
from flockcal.solver.reconstruct import Articulation, ArticulationError


@dataclass(frozen=True)
class Skeleton:
    """A validated skeleton file (`flockcal.exports.skeleton.load_skeleton`): the saved tree, ready to fit a new
    take of the same performer with `known_fit`."""

    data: dict
    articulation: Articulation  # the tree with its joint centres, built on parsing

    @property
    def names(self) -> tuple[str, ...]:
        return self.articulation.names

    @property
    def root(self) -> str:
        return self.articulation.names[self.articulation.root]

    @property
    def hierarchy(self) -> dict[str, str]:
        """{child: parent}, root omitted: what `calibrate(..., hierarchy=)` and `--hierarchy` take."""
        return dict(self.data["parent"])

    @property
    def bone_stderr(self) -> dict[tuple[str, str], float]:
        out = {}
        for b in self.data["bones"]:
            if isinstance(b.get("stderr_m"), (int, float)):
                out[(b["from_joint"], b["to_joint"])] = out[(b["to_joint"], b["from_joint"])] = float(b["stderr_m"])
        return out

    @property
    def source(self) -> dict:
        """What the file says it was calibrated from (`source`: session, performer, take, frames, rate_hz), {}
        when it says nothing."""
        source = self.data.get("source")
        return source if isinstance(source, dict) else {}

    @property
    def performers(self) -> tuple[tuple[str, object], ...]:
        """(where, value) of each performer name the file gives, as written: top level, then its source's."""
        return (("performer", self.data.get("performer")), ("source.performer", self.source.get("performer")))

    @property
    def performer(self) -> str | None:
        """The performer the file names (top level, else its source's), if it names one."""
        name = next((v for _, v in self.performers if v), None)
        return name if isinstance(name, str) and name.strip() else None

    @property
    def created_utc(self) -> str | None:
        return self.data.get("created_utc")

    @property
    def bone_count(self) -> int:
        return len(self.data.get("bones", []))

    @property
    def bone_keys(self) -> frozenset:
        """(from_joint, to_joint) of every bone the file holds: the ones its take measured."""
        return frozenset((b["from_joint"], b["to_joint"]) for b in self.data["bones"])

    def check_names(self, names) -> None:
        """SkeletonError unless the take's sensors are exactly the skeleton's (any order)."""
        try:
            self.articulation.reordered(names)
        except ValueError as exc:  # the solver's ArticulationError, a ValueError: names that do not match
            raise SkeletonError(f"skeleton does not match the take: {exc}") from None


def body_points(art: Articulation) -> list[tuple[list[int], np.ndarray]]:
    """Per body: the joints (named by child index) it holds and their centres (k, 3) in its frame."""
    out = []
    for b in range(art.n_bodies):
        joints = ([b] if art.parent[b] >= 0 else []) + art.children(b)
        pts = [art.c[b]] if art.parent[b] >= 0 else []
        pts += [art.l[k] for k in art.children(b)]
        out.append((joints, np.array(pts).reshape(-1, 3)))
    return out


def bone_arrays(art: Articulation, stderr: dict[tuple[str, str | None], float] | None = None,
                only: frozenset | None = None) -> Bones:
    """docs/design.md §5 bones of `art`: per body, inboard joint to each outboard joint (root: pairs of outboard
    joints); `only` keeps just the bones whose (from_joint, to_joint) names it holds (a file's measured bones)."""
    rows = []
    names = art.names
    rigid = art.rigid if art.rigid is not None else np.zeros(art.n_bodies, dtype=bool)
    for b in art.order:
        b = int(b)
        kids = art.children(b)
        at_root = art.parent[b] < 0
        if not at_root:
            spans = [(b, art.c[b], k, art.l[k]) for k in kids]
        else:
            spans = [(k1, art.l[k1], k2, art.l[k2]) for n1, k1 in enumerate(kids) for k2 in kids[n1 + 1 :]]
        for a, pa, k, pk in spans:
            if rigid[a] or rigid[k]:
                continue  # a rigidly attached sensor has no joint, only a stand-in point at the sensor
            key = (names[a], names[k])
            if only is not None and key not in only:
                continue
            rows.append((b, a, k, float(np.linalg.norm(pk - pa)), float((stderr or {}).get(key, float("nan"))), at_root))
    if not rows:
        z = np.zeros(0)
        return Bones(z.astype(int), z.astype(int), z.astype(int), z, z, z.astype(bool))
    body, frm, to, length, err, root = (np.array(x) for x in zip(*rows))
    return Bones(body.astype(int), frm.astype(int), to.astype(int), length.astype(float), err.astype(float),
                 root.astype(bool))


def bones(art: Articulation, stderr: dict[tuple[str, str | None], float] | None = None,
          only: frozenset | None = None) -> list[dict]:
    """`bone_arrays` as the §5 JSON `bones` list."""
    return bones_json(bone_arrays(art, stderr, only), art.names)


def rigid_fit(old: np.ndarray, new: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation Q and shift s minimising Σ‖Q old + s − new‖² (Kabsch); Q = I for a single point."""
    if len(old) < 2:
        return np.eye(3), (new - old).mean(axis=0) if len(old) else np.zeros(3)
    po, pn = old.mean(axis=0), new.mean(axis=0)
    U, _, Vt = np.linalg.svd((old - po).T @ (new - pn))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0])
    Q = Vt.T @ D @ U.T
    return Q, pn - Q @ po


@dataclass(frozen=True)
class KnownFit:
    """A take fitted with a saved skeleton: the fit's state (what a live refresh starts from) and, through
    `calibration()`, the solver's result; `to_dict()` is its docs/design.md §5 JSON."""

    articulation: Articulation  # saved bones, this take's placements
    frames: int
    rms: np.ndarray  # (m,) per tree joint (indexed by child; NaN at the root), metres
    epsilon: np.ndarray  # (m,)
    rms_free: np.ndarray  # (m,) the same joint fitted freely: a much smaller value says the skeleton no longer fits
    iterations: int
    free: PairFits | None = None  # the tree joints fitted freely, in `articulation.order[1:]`
    bone_stderr: dict = field(default_factory=dict)
    motion: tuple | None = None  # (Q (m,3,3), s (m,3)): saved body points → this take's sensor frames
    bone_keys: frozenset | None = None  # the bones the saved file measured: (from_joint, to_joint); None: all

    def calibration(self, segment_start_s: np.ndarray | None = None) -> Calibration:
        """The fit as the solver's `Calibration`: saved topology and bones, this take's c, l and residuals;
        every other joint field (singular values, hinge, coverage, …) from the free fit of the same joint.
        `segment_start_s` (per joint, NaN: whole take) marks joints refitted after a slip."""
        art = self.articulation
        child = np.array([int(j) for j in art.order[1:]], dtype=int)
        free = self.free if self.free is not None else unfitted(np.stack([child, art.parent[child]], axis=1))
        joints = replace(free, c=art.c[child], l=art.l[child], rms=self.rms[child], epsilon=self.epsilon[child])
        placement = np.full((art.n_bodies, 3), np.nan)
        placement[child] = art.c[child]
        return Calibration(tuple(art.names), int(art.root), np.asarray(art.parent), np.asarray(art.order),
                           int(self.frames), joints, bone_arrays(art, self.bone_stderr, self.bone_keys), placement,
                           hierarchy_given=True, known_skeleton=True, rms_free=self.rms_free[child],
                           segment_start_s=segment_start_s)

    def to_dict(self) -> dict:
        return self.calibration().to_dict()


def _joint_sse(A, b, dd, u):
    return np.einsum("pi,pij,pj->p", u, A, u) - 2 * np.einsum("pi,pi->p", b, u) + dd


def fit_known_skeleton(
    acc,
    saved: Articulation,
    names,
    iterations: int = 20,
    bone_stderr: dict | None = None,
    previous: KnownFit | None = None,
    bone_keys: frozenset | None = None,
) -> KnownFit:
    """Fit the accumulated take (sensor order `names`) with `saved`'s topology and bone lengths.

    `acc` is a `GramAccumulator`; only its normal equations for the tree joints are read, so this costs
    a handful of 6m×6m solves whatever the take's length. A live refresh passes the `previous` result
    (same skeleton, same names) to start from it: usually one or two Gauss–Newton steps then.
    """
    from scipy.spatial.transform import Rotation  # here: scipy.spatial costs every `flockcal fit` ~0.3 s to import

    from flockcal.solver.calibration import placed_hinges
    from flockcal.solver.fits import pair_fits

    art = saved.reordered(names)
    m = art.n_bodies
    if acc.n_sensors != m:
        raise ArticulationError(f"the accumulator has {acc.n_sensors} sensors, the skeleton {m}")
    art = art.completed(acc=acc)
    child = np.array([int(j) for j in art.order[1:]])
    par = art.parent[child]
    pairs = np.stack([child, par], axis=1)
    A, bvec, dd, nfr = (np.asarray(x, dtype=float) for x in acc.normal_equations(pairs))
    if np.any(nfr < 1):
        lacking = [art.names[j] for j, k in zip(child, nfr) if k < 1]
        raise ArticulationError(f"no frame has both sensors of joint(s) {', '.join(lacking)} valid")
    # Hinges' centres by the same rule the saved skeleton was fitted with (solver/hinge_point.py): the
    # Procrustes start below matches saved points to these, and a minimum-norm point along an axis would
    # turn a body with two joints.
    free, _ = placed_hinges(acc, pair_fits(acc, pairs))
    free_c = np.asarray(free.c, dtype=float)
    free_l = np.asarray(free.l, dtype=float)

    if previous is not None and previous.motion is not None and previous.articulation.names == art.names:
        Q, s = (np.array(x, dtype=float) for x in previous.motion)
    else:
        # Procrustes start: each body's saved joint points onto the same joints of the free fit.
        row = {int(j): r for r, j in enumerate(child)}
        Q = np.broadcast_to(np.eye(3), (m, 3, 3)).copy()
        s = np.zeros((m, 3))
        for bdy, (joints, old) in enumerate(body_points(art)):
            new = np.array([free_c[row[k]] if k == bdy else free_l[row[k]] for k in joints]).reshape(-1, 3)
            Q[bdy], s[bdy] = rigid_fit(old, new)

    def placed(Q, s):
        c = np.einsum("pab,pb->pa", Q[child], art.c[child]) + s[child]
        l = np.einsum("pab,pb->pa", Q[par], art.l[child]) + s[par]
        return c, l

    # Gauss–Newton on Σ SSE_j over per-body rigid motions (ω, δs); the cost is exactly quadratic in the
    # joint points, so only the rotations' curvature is linearised. Free directions (a leaf spinning
    # about its one joint, a joint sliding along its hinge axis) stay where Procrustes put them.
    # A hinge's centre slides along its axis at almost no cost in the data, and with it the bodies on
    # either side turn about their other joints: the data's noise, not the motion, would place it. The
    # hinge rule's point (the free fit above, solver/hinge_point.py) is counted as one more measurement
    # along each hinge axis with the rule's own sd, weighted against the joint's residual variance per
    # coordinate: a target that depends on the data alone, so a warm and a cold start agree.
    hinge = np.asarray(free.hinge, dtype=bool) & np.isfinite(np.asarray(free.axis_i, dtype=float)).all(axis=1)
    ax_c = np.where(hinge[:, None], np.nan_to_num(np.asarray(free.axis_i, dtype=float)), 0.0)
    ax_l = np.where(hinge[:, None], np.nan_to_num(np.asarray(free.axis_j, dtype=float)), 0.0)
    # SSE/σ² + s²/sd² in SSE units, σ² the residual variance per coordinate; half on each side's point.
    w_axis = np.where(hinge, np.nan_to_num(np.asarray(free.rms, dtype=float)) ** 2 / (3.0 * LIMB_RULE_SD_M ** 2)
                      / 2.0, 0.0)
    c0, l0 = free_c, free_l

    def prior(c, l):
        return w_axis * (np.einsum("pi,pi->p", c - c0, ax_c) ** 2 + np.einsum("pi,pi->p", l - l0, ax_l) ** 2)

    def cost(Q, s):
        c, l = placed(Q, s)
        return _joint_sse(A, bvec, dd, np.concatenate([c, l], axis=1)) + prior(c, l)

    sse = cost(Q, s)
    done = 0
    for done in range(1, iterations + 1):
        c, l = placed(Q, s)
        Qc = c - s[child]
        Ql = l - s[par]
        Jc = np.concatenate([-skew(Qc), np.broadcast_to(np.eye(3), Qc.shape + (3,))], axis=2)  # (p, 3, 6)
        Jl = np.concatenate([-skew(Ql), np.broadcast_to(np.eye(3), Ql.shape + (3,))], axis=2)
        r = np.einsum("pij,pj->pi", A, np.concatenate([c, l], axis=1)) - bvec  # ½ gradient in u
        Pc = w_axis[:, None, None] * np.einsum("pi,pj->pij", ax_c, ax_c)
        Pl = w_axis[:, None, None] * np.einsum("pi,pj->pij", ax_l, ax_l)
        r = r + np.concatenate([np.einsum("pij,pj->pi", Pc, c - c0), np.einsum("pij,pj->pi", Pl, l - l0)], axis=1)
        A_step = A.copy()
        A_step[:, :3, :3] += Pc
        A_step[:, 3:, 3:] += Pl
        H = np.zeros((m, m, 6, 6))
        g = np.zeros((m, 6))
        Acc, Acl, All = A_step[:, :3, :3], A_step[:, :3, 3:], A_step[:, 3:, 3:]
        np.add.at(H, (child, child), np.swapaxes(Jc, 1, 2) @ Acc @ Jc)
        np.add.at(H, (par, par), np.swapaxes(Jl, 1, 2) @ All @ Jl)
        cross = np.swapaxes(Jc, 1, 2) @ Acl @ Jl
        np.add.at(H, (child, par), cross)
        np.add.at(H, (par, child), np.swapaxes(cross, 1, 2))
        np.add.at(g, child, np.einsum("pia,pi->pa", Jc, r[:, :3]))
        np.add.at(g, par, np.einsum("pia,pi->pa", Jl, r[:, 3:]))
        Hf = H.transpose(0, 2, 1, 3).reshape(6 * m, 6 * m)
        # A tiny ridge (Levenberg–Marquardt) keeps the free directions still: the gradient has no
        # component along them, so the step there is ~0. LU solve, not lstsq: 96×96 either way, but
        # SVD-based lstsq is slow under a threaded BLAS on a busy machine.
        ridge = 1e-9 * max(float(np.trace(Hf)) / len(Hf), 1e-300)
        step = np.linalg.solve(Hf + ridge * np.eye(len(Hf)), -g.reshape(-1)).reshape(m, 6)
        improved = False
        for shrink in (1.0, 0.5, 0.25, 0.125):
            dQ = Rotation.from_rotvec(shrink * step[:, :3]).as_matrix()
            Qn, sn = dQ @ Q, s + shrink * step[:, 3:]
            new = cost(Qn, sn)
            if new.sum() <= sse.sum():
                improved = sse.sum() - new.sum() > 1e-12 * max(sse.sum(), 1e-30)
                Q, s, sse = Qn, sn, new
                break
        if not improved:
            break

    c, l = placed(Q, s)
    C = np.zeros((m, 3))
    L = np.zeros((m, 3))
    C[child], L[child] = c, l
    fitted = Articulation(art.names, art.parent, C, L, art.order, art.rigid)
    rms = np.full(m, np.nan)
    eps = np.full(m, np.nan)
    rms_free = np.full(m, np.nan)
    sse = np.maximum(_joint_sse(A, bvec, dd, np.concatenate([c, l], axis=1)), 0.0)  # the data's alone
    rms[child] = np.sqrt(sse / nfr)
    eps[child] = np.sqrt(sse) / nfr
    rms_free[child] = np.asarray(free.rms, dtype=float)
    return KnownFit(fitted, int(acc.frames), rms, eps, rms_free, done, free, dict(bone_stderr or {}), (Q, s),
                    bone_keys)


def saved_placement(skeleton, names) -> KnownFit:
    """A stand-in previous fit that starts the Gauss–Newton at the saved placements themselves."""
    art = skeleton.articulation.reordered(list(names))
    m = art.n_bodies
    nan = np.full(m, np.nan)
    return KnownFit(art, 0, nan, nan, nan, 0, motion=(np.broadcast_to(np.eye(3), (m, 3, 3)).copy(), np.zeros((m, 3))))


def fit_saved(skeleton, acc, names, previous: KnownFit | None = None) -> KnownFit:
    """Fit an accumulated take (sensor order `names`) with a saved `skeleton` (a `Skeleton`);
    a live refresh passes the last KnownFit as `previous` to start from it."""
    skeleton.check_names(names)
    return fit_known_skeleton(acc, skeleton.articulation, names, bone_stderr=skeleton.bone_stderr,
                              previous=previous, bone_keys=skeleton.bone_keys)


def known_fit(skeleton, acc, names, previous: KnownFit | None = None) -> KnownFit:
    """`fit_saved` on a session's accumulator (a segmented one, after slips, through its `pair_view`).

    A cold fit tries two starts and keeps the better: the solver's own (each body's saved points moved
    onto the free joint fits) and the saved placements as they are. On a tie — a body whose joints have
    not moved yet, so the data cannot place it — the saved placement wins instead of an arbitrary one:
    early in a take the unexercised limbs stay where the performer's file put them."""
    view = acc.pair_view()
    names = list(names)
    if previous is not None:
        return fit_saved(skeleton, view, names, previous=previous)
    anchored = fit_saved(skeleton, view, names, previous=saved_placement(skeleton, names))
    free = fit_saved(skeleton, view, names)
    cost_anchored, cost_free = (float(np.nansum(f.rms ** 2)) for f in (anchored, free))
    return anchored if cost_anchored <= cost_free * (1 + 1e-6) + 1e-12 else free


def known_calibration(fit: KnownFit, acc) -> Calibration:
    """`fit.calibration()`, its joints refitted on a segment of `acc` marked `segment_start_s` as in free fits."""
    cal = fit.calibration()
    if not acc.segments:
        return cal
    segs = acc.pair_segments(cal.joints.pairs)
    start = np.array([np.nan if s is None else s.start_s for s in segs], dtype=float)
    return replace(cal, segment_start_s=start)
