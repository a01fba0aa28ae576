"""Joints for markers fixed on their bones: every body's pose in every frame and every joint's offsets in its
two bodies, fitted together to the markers (a bundle adjustment). A body of one or two markers has its turn
about its markers' line pinned only by its joints together, so the joints around it are adjusted as one set;
every other joint with its two bodies alone."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flockcal.solver.optical.fixed_hinges import relative_hinge
from flockcal.solver.optical.joints import points_for_radii, usable_frames
from flockcal.solver.optical.rigid import apply, procrustes_mean, rigid_fit, to_body

FRAMED = 3  # markers a body needs for a pose of its own

# A joint's two offsets coincide exactly (no noise of their own): their mismatch counts this many times a
# marker's, tight against the markers' noise without a hard constraint's ill-conditioning.
JOINT_WEIGHT = 10.0

# A penalty on the offsets' size, as Kirk's on the radii (joints.py): it keeps the steps finite along a
# direction the data leave free (a hinge's axis, before the hinge is known and held); small enough not to
# pull a ball's centre along the direction the take turned least (Kirk's 1e-5 pulled a walk's hip 4–5 mm
# towards the markers).
PENALTY = 1e-8

# The adjustment stops once a step gains less than this share of the cost (the markers' noise summed over
# the frames): past it the steps crawl along a flat valley (a ball turned mostly about one axis), each
# gaining some 9 % less than the last. At 1e-6 a simulated exercise take's largest bundle took 73 such
# steps and the fit 17 s of CPU (8 s at 1e-5); over six such takes the worst bone moved by 0.03 mm or
# less, on one from 2.5 to 1.9 mm.
STEP_GAIN = 1e-5
DEBUG = False


@dataclass(frozen=True)
class Bundle:
    """The bodies and joints of one bundle: `bodies` (global body ids), `joints` (child ids) with the
    positions in `bodies` of each joint's child and parent."""

    bodies: list[int]
    joints: list[int]
    child: np.ndarray  # (J,) position in `bodies`
    parent: np.ndarray  # (J,)


def bundles(groups: list[np.ndarray], parent: np.ndarray, joints) -> list[Bundle]:
    """The tree joints `joints` (children) in sets, each with every body its joints touch: joints joined
    through a body of fewer than FRAMED markers together (such a body's turn about its markers' line is
    pinned only by its joints together), every other joint alone with its two bodies."""
    joints = sorted({int(c) for c in joints})
    root = {c: c for c in joints}

    def find(c):
        while root[c] != c:
            root[c] = root[root[c]]
            c = root[c]
        return c

    for a in joints:
        for c in joints:
            shared = {a, int(parent[a])} & {c, int(parent[c])}
            if a < c and any(len(groups[b]) < FRAMED for b in shared):
                root[find(c)] = find(a)
    out = []
    for top in dict.fromkeys(find(c) for c in joints):
        js = [c for c in joints if find(c) == top]
        bodies = sorted({b for c in js for b in (c, int(parent[c]))})
        out.append(Bundle(bodies, js, np.array([bodies.index(c) for c in js]),
                          np.array([bodies.index(int(parent[c])) for c in js])))
    return out


def skew(x: np.ndarray) -> np.ndarray:
    """[x]× for (..., 3) vectors."""
    z = np.zeros(x.shape[:-1])
    return np.stack([np.stack([z, -x[..., 2], x[..., 1]], -1), np.stack([x[..., 2], z, -x[..., 0]], -1),
                     np.stack([-x[..., 1], x[..., 0], z], -1)], -2)


def rotvec_matrix(w: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of rotation vectors w (..., 3) (Rodrigues)."""
    th = np.linalg.norm(w, axis=-1)[..., None, None]
    K = skew(w)
    small = th < 1e-12
    a = np.where(small, 1.0, np.sin(th) / np.where(small, 1.0, th))
    b = np.where(small, 0.5, (1 - np.cos(th)) / np.where(small, 1.0, th) ** 2)
    return np.eye(3) + a * K + b * (K @ K)


def normal_equations(markers, shapes, bundle: Bundle, R, t, x):
    """Gauss–Newton blocks over the frames: A (F,6G,6G) of the poses (rotation increments in the world
    frame, then translations), X (F,6G,6J) between poses and offsets, C (6J,6J) of the offsets; gradients
    (F,6G) and (6J,), and the cost. x (J, 2, 3): each joint's offset in its child's and its parent's frame."""
    F = len(R)
    G, J = len(bundle.bodies), len(bundle.joints)
    A = np.zeros((F, G, 6, G, 6))
    g = np.zeros((F, G, 6))
    cost = 0.0
    eye = np.broadcast_to(np.eye(3), (F, 3, 3))
    for k, (pts, shape) in enumerate(zip(markers, shapes)):
        seen = np.isfinite(pts).all(-1)  # (F, q)
        Rs = R[:, k] @ shape.T  # (F, 3, q)
        e = np.where(seen[:, None], Rs + t[:, k, :, None] - np.nan_to_num(pts).transpose(0, 2, 1), 0.0)  # (F,3,q)
        # Σ over markers of [−[Rs]×, I]ᵀ[−[Rs]×, I], written out: Σ[p]×ᵀ[p]× = Σ(|p|² I − p pᵀ), Σ[p]×ᵀ = −[Σp]×.
        Rs = Rs * seen[:, None]
        n = seen.sum(1).astype(float)
        sp = Rs.sum(2)
        pp = Rs @ Rs.transpose(0, 2, 1)
        A[:, k, :3, k, :3] += np.trace(pp, axis1=1, axis2=2)[:, None, None] * np.eye(3) - pp
        A[:, k, :3, k, 3:] += skew(sp)
        A[:, k, 3:, k, :3] += -skew(sp)
        A[:, k, 3:, k, 3:] += n[:, None, None] * np.eye(3)
        g[:, k, :3] += np.cross(Rs.transpose(0, 2, 1), e.transpose(0, 2, 1)).sum(1)  # Σ −[p]×ᵀ e = Σ p × e
        g[:, k, 3:] += e.sum(2)
        cost += float((e**2).sum())
    X = np.zeros((F, G, 6, J, 6))
    C = np.zeros((J, 6, J, 6))
    gx = np.zeros((J, 6))
    w = JOINT_WEIGHT
    for j in range(J):
        a, b = bundle.child[j], bundle.parent[j]
        pa, pb = R[:, a] @ x[j, 0], R[:, b] @ x[j, 1]
        e = w * (pa + t[:, a] - pb - t[:, b])
        Ja = w * np.concatenate([-skew(pa), eye], axis=-1)  # (F,3,6)
        Jb = -w * np.concatenate([-skew(pb), eye], axis=-1)
        Jx = np.concatenate([w * R[:, a], -w * R[:, b]], axis=-1)  # (F,3,6): ∂e/∂(x_child, x_parent)
        for (k, Jk) in ((a, Ja), (b, Jb)):
            JkT = Jk.transpose(0, 2, 1)
            g[:, k] += (JkT @ e[..., None])[..., 0]
            X[:, k, :, j] += JkT @ Jx
            A[:, k, :, a] += JkT @ Ja
            A[:, k, :, b] += JkT @ Jb
        JxT = Jx.transpose(0, 2, 1)
        C[j, :, j] += (JxT @ Jx).sum(0)
        gx[j] += (JxT @ e[..., None])[..., 0].sum(0) + PENALTY * F * x[j].ravel()
        C[j, :, j] += PENALTY * F * np.eye(6)
        cost += float((e**2).sum()) + PENALTY * F * float((x[j] ** 2).sum())
    return (A.reshape(F, 6 * G, 6 * G), X.reshape(F, 6 * G, 6 * J), C.reshape(6 * J, 6 * J),
            g.reshape(F, 6 * G), gx.reshape(6 * J), cost)


def step(R, t, x, dp, dx):
    """Poses turned and moved by dp (F, G, 6), offsets by dx (J, 2, 3)."""
    return rotvec_matrix(dp[..., :3]) @ R, t + dp[..., 3:], x + dx


def free_basis(hold: np.ndarray) -> np.ndarray:
    """(6J, m) an orthonormal basis of the offsets' steps that keep each offset's coordinate along its
    direction in `hold` (J, 2, 3) (zero: every step)."""
    from scipy.linalg import block_diag, null_space

    return block_diag(*(np.eye(3) if not d.any() else null_space(d[None]) for d in hold.reshape(-1, 3)))


def adjust(markers, shapes, bundle: Bundle, R, t, x, max_iter: int = 100, tol: float = STEP_GAIN, hold=None):
    """Levenberg–Marquardt on the bundle: the frames' poses eliminated by a Schur complement. hold: None or
    (J, 2, 3) a direction per offset (zero: none) along which the offset keeps its coordinate."""
    F, G = R.shape[:2]
    J = len(bundle.joints)
    mu = 1e-4
    free = free_basis(np.zeros((J, 2, 3)) if hold is None else hold)
    A, X, C, g, gx, cost = normal_equations(markers, shapes, bundle, R, t, x)
    steps = 0
    while steps < max_iter:
        dA = np.diagonal(A, axis1=1, axis2=2)
        Ai = np.linalg.inv(A + (mu * np.maximum(dA, 1e-9) + 1e-12)[..., None] * np.eye(6 * G))
        AiX, Aig = Ai @ X, (Ai @ g[..., None])[..., 0]
        S = C + mu * np.diag(np.maximum(np.diag(C), 1e-9)) - np.einsum("fig,fih->gh", X, AiX)
        dx = free @ np.linalg.lstsq(free.T @ S @ free, free.T @ (-gx + np.einsum("fig,fi->g", X, Aig)), rcond=None)[0]
        dp = -(Aig + AiX @ dx)
        Rn, tn, xn = step(R, t, x, dp.reshape(F, G, 6), dx.reshape(J, 2, 3))
        new = normal_equations(markers, shapes, bundle, Rn, tn, xn)
        if new[-1] > cost:
            mu *= 10
            if mu > 1e8:
                break
            continue
        gain = cost - new[-1]
        R, t, x = Rn, tn, xn
        A, X, C, g, gx, cost = new
        mu = max(mu / 10, 1e-9)
        steps += 1
        if gain <= tol * max(cost, 1e-30):
            break
    if DEBUG:
        print("bundle steps", steps, "cost", cost)
    return R, t, x


def lent_poses(markers: np.ndarray, groups: list[np.ndarray], bundle: Bundle, points: dict[int, np.ndarray]):
    """Starting poses (F,G,3,3), (F,G,3), ok (F,G) and shapes: a framed body's from its markers; a body of
    fewer markers from its markers and its joints' points already placed, each joint's point its median
    position in a posed body's frame carried by that pose (outward from the framed bodies). `points`: each
    joint's own Kirk fit (F, 3), whose point may land on either side of a circle frame by frame."""
    F = len(markers)
    G = len(bundle.bodies)
    R = np.tile(np.eye(3), (F, G, 1, 1))
    t = np.zeros((F, G, 3))
    ok = np.zeros((F, G), dtype=bool)
    shapes: list = [None] * G
    placed: dict[int, np.ndarray] = {}
    for k, b in enumerate(bundle.bodies):
        if len(groups[b]) >= FRAMED:
            shapes[k], R[:, k], t[:, k], ok[:, k] = procrustes_mean(markers[:, groups[b]])
    while True:
        grew = False
        for j, c in enumerate(bundle.joints):
            side = next((k for k in (bundle.child[j], bundle.parent[j]) if shapes[k] is not None), None)
            if j in placed or side is None:
                continue
            o = ok[:, side]
            local = np.nanmedian(to_body(R[o, side], t[o, side], points[c][o][:, None])[:, 0], axis=0)
            placed[j] = np.where(o[:, None], apply(R[:, side], t[:, side], local[None])[:, 0], np.nan)
            grew = True
        for k, b in enumerate(bundle.bodies):
            mine = [j for j in placed if k in (bundle.child[j], bundle.parent[j])]
            if shapes[k] is not None or not mine:
                continue
            pts = np.concatenate([markers[:, groups[b]], np.stack([placed[j] for j in mine], axis=1)], axis=1)
            shape, R[:, k], t[:, k], ok[:, k] = procrustes_mean(pts)
            shapes[k] = shape[: len(groups[b])]
            grew = True
        if not grew:
            return R, t, ok, shapes


def offsets(bundle: Bundle, R, t, ok, points: dict[int, np.ndarray]) -> np.ndarray:
    """(J, 2, 3) each joint's point (its own fit) as a median offset in its child's and its parent's frame."""
    x = np.zeros((len(bundle.joints), 2, 3))
    for j, c in enumerate(bundle.joints):
        for s, k in enumerate((bundle.child[j], bundle.parent[j])):
            o = ok[:, k] & np.isfinite(points[c]).all(1)
            x[j, s] = np.median(to_body(R[o, k], t[o, k], points[c][o][:, None])[:, 0], axis=0) if o.any() else 0.0
    return x


def chain_poses(markers: np.ndarray, groups: list[np.ndarray], bundle: Bundle, shapes: list, x: np.ndarray):
    """Poses (n,G,3,3), (n,G,3), ok (n,G) on every frame from the bundle's offsets x: a framed body's from its
    markers, a body of fewer markers from its markers and the points of its joints to bodies already posed."""
    n, G = len(markers), len(bundle.bodies)
    R = np.tile(np.eye(3), (n, G, 1, 1))
    t = np.zeros((n, G, 3))
    ok = np.zeros((n, G), dtype=bool)
    posed = set()
    for k, b in enumerate(bundle.bodies):
        if len(groups[b]) >= FRAMED:
            R[:, k], t[:, k], ok[:, k] = rigid_fit(shapes[k], markers[:, groups[b]])
            posed.add(k)
    while len(posed) < G:
        grew = False
        for k, b in enumerate(bundle.bodies):
            if k in posed:
                continue
            ref, pts = [shapes[k]], [markers[:, groups[b]]]
            for j in range(len(bundle.joints)):
                for me, other in ((0, 1), (1, 0)):
                    ends = (bundle.child[j], bundle.parent[j])
                    if ends[me] == k and ends[other] in posed:
                        o = ends[other]
                        p = apply(R[:, o], t[:, o], x[j, other][None])
                        pts.append(np.where(ok[:, o, None, None], p, np.nan))
                        ref.append(x[j, me][None])
            if len(ref) > 1:
                R[:, k], t[:, k], ok[:, k] = rigid_fit(np.concatenate(ref), np.concatenate(pts, axis=1))
                posed.add(k)
                grew = True
        if not grew:
            break
    return R, t, ok


def bundle_joint_points(markers: np.ndarray, groups: list[np.ndarray], bundle: Bundle, points: dict[int, np.ndarray],
                        frames: np.ndarray, max_iter: int = 100) -> dict[int, np.ndarray]:
    """{child: (n, 3) world joint centre per frame} for the bundle's joints: the offsets adjusted on `frames`
    (those where every body of the bundle has a starting pose), every frame's poses then chained from them
    (`chain_poses`), each joint the mean of its two bodies' placing of it (NaN where neither has a pose).
    `points`: each joint's own Kirk fit on `frames`, the start."""
    M = markers[frames]
    R, t, ok, shapes = lent_poses(M, groups, bundle, points)
    if any(s is None for s in shapes):
        return {}
    use = ok.all(1)
    if use.sum() < 10:
        return {}
    x = offsets(bundle, R[use], t[use], ok[use], {c: p[use] for c, p in points.items()})
    own = [M[use][:, groups[b]] for b in bundle.bodies]
    R, t, x = adjust(own, shapes, bundle, R[use], t[use], x, max_iter)
    # Every frame's poses (consecutive frames: the hinge test reads the noise from them); a hinge's point is
    # then taken along its axis to where it passes its two bodies' markers (the centroids of each body's,
    # split evenly: the minimum-norm point, design.md §3c) and held there (design.md §3a: along a direction
    # the joint did not turn about beyond noise, least squares fits noise). Unheld, the bundle carried a
    # simulated knee 100 mm along its axis, and the rule slid it back along an axis a few degrees off, 6 mm
    # off the bone. Kirk's start is no such point: it put a knee between two bodies of two markers 72 mm along
    # the axis, where its point in each frame, from four distances, scattered and bent those bodies' shapes;
    # the rule then placed it 50 mm off.
    Rn, tn, okn = chain_poses(markers, groups, bundle, shapes, x)
    axes = np.zeros((len(bundle.joints), 2, 3))
    for j in range(len(bundle.joints)):
        a, b = bundle.child[j], bundle.parent[j]
        hinge, axes[j, 0], axes[j, 1] = relative_hinge(Rn[:, a], okn[:, a], Rn[:, b], okn[:, b])
        if not hinge:
            axes[j] = 0.0
    if axes.any():
        centre = np.stack([[shapes[k].mean(0) for k in (bundle.child[j], bundle.parent[j])] for j in range(len(axes))])
        back = 0.5 * np.einsum("jsa,jsa->j", centre - x, axes)  # both offsets by one slide: the joint stays one
        x = x + back[:, None, None] * axes
        # The poses restarted from the slid points: a body of two markers turns about their line with them.
        Rc, tc, okc = chain_poses(M[use], groups, bundle, shapes, x)
        R, t = np.where(okc[..., None, None], Rc, R), np.where(okc[..., None], tc, t)
        R, t, x = adjust(own, shapes, bundle, R, t, x, max_iter, hold=axes)
        Rn, tn, okn = chain_poses(markers, groups, bundle, shapes, x)
    R, t, ok = Rn, tn, okn
    out = {}
    for j, c in enumerate(bundle.joints):
        # Each frame's point from its distances to both bodies' markers (fixed by the offsets found), started
        # where the chained poses put it: sharper than those poses, which carry a framed body's turn at the joint.
        ends = (bundle.child[j], bundle.parent[j])
        side = [np.where(ok[:, k, None], apply(R[:, k], t[:, k], x[j, s][None])[:, 0], np.nan) for s, k in enumerate(ends)]
        start = np.where(np.isfinite(side[0]) & np.isfinite(side[1]), 0.5 * (side[0] + side[1]),
                         np.where(np.isfinite(side[0]), side[0], side[1]))
        radii = np.concatenate([np.linalg.norm(shapes[k] - x[j, s], axis=1) for s, k in enumerate(ends)])
        cols = np.concatenate([groups[bundle.bodies[k]] for k in ends])
        # The frames Kirk's fit would use (each body shows a marker, four in all): with three distances the
        # point has two places, as it has in Kirk's fit.
        a, b = (groups[bundle.bodies[k]] for k in ends)
        has = np.zeros(len(markers), dtype=bool)
        has[usable_frames(markers[:, a], markers[:, b])] = True
        has &= np.isfinite(start).all(1)
        p = np.full((len(markers), 3), np.nan)
        p[has], res = points_for_radii(markers[has][:, cols], radii, start[has])
        before = np.linalg.norm(markers[has][:, cols] - start[has][:, None], axis=-1) - radii
        worse = np.nanmean(res**2, axis=1) > np.nanmean(before**2, axis=1)
        p[np.flatnonzero(has)[worse]] = start[has][worse]
        out[c] = p
    return out
