"""Joint points from markers alone (Kirk et al. 2005 §3): the point that keeps a constant distance to
every marker of two rigid groups, per frame, and the skeleton tree as the MST of those fits' residuals.

For groups A, B with markers a ∈ A∪B: minimise Σ_k Σ_a (‖m_a,k − p_k‖ − r_a)² + λ n Σ_a r_a² over the
per-frame points p_k and the constant radii r_a (scipy least_squares, sparse Jacobian). The small λ keeps
a nearly planar motion from sending p to infinity; the final fit on all frames drops it.

The Jacobian is sparse in a fixed pattern (a residual touches one frame's p and one r), so the solver is
Levenberg–Marquardt with the frames eliminated by a Schur complement: one q×q solve per iteration, all
3×3 frame blocks inverted at once. scipy's least_squares with a sparse Jacobian (trf/lsmr) minimises the
same cost and agrees, but was ~40× slower here (lsmr iterations dominate).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flockcal.solver.optical.rigid import nanmean, procrustes_mean, to_body


@dataclass(frozen=True)
class JointPoint:
    points: np.ndarray  # (n, 3) joint point per frame, world metres; NaN where the frame was not usable
    radii: np.ndarray  # (q,) constant distance to each marker of A∪B (A's first)
    rms: float  # rms of ‖m − p‖ − r over used marker-frames (m)
    frames: np.ndarray  # (f,) frames used
    residuals: np.ndarray  # (n, q) ‖m − p‖ − r, NaN where unseen or unused


def usable_frames(markers_a: np.ndarray, markers_b: np.ndarray) -> np.ndarray:
    """Frames where each group shows a marker and A∪B shows at least four (p then has redundancy)."""
    va = np.isfinite(markers_a).all(-1)
    vb = np.isfinite(markers_b).all(-1)
    return np.flatnonzero(va.any(1) & vb.any(1) & (va.sum(1) + vb.sum(1) >= min(4, va.shape[1] + vb.shape[1])))


def sphere_centre_guess(markers_a: np.ndarray, markers_b: np.ndarray, frames: np.ndarray, poses=None):
    """Initial joint points (f,3) for `frames`, or None: B's markers seen from A's frame lie on spheres
    about the joint, so one linear solve (shared centre c, per-marker r² − ‖c‖²) finds it.

    Needs a group with three or more markers to give a frame; the larger one is used. `poses`: a callable
    giving (R, t, ok) of a group's markers (n, q, 3) on `frames`, to share one group's pose between pairs.
    """
    A, Bm = markers_a[frames], markers_b[frames]
    if A.shape[1] < Bm.shape[1]:
        A, Bm = Bm, A
    if A.shape[1] < 3:
        return None
    R, t, ok = procrustes_mean(A)[1:] if poses is None else poses(A)
    if ok.sum() < 10:
        return None
    y = to_body(R[ok], t[ok], Bm[ok])  # (f', qb, 3)
    seen = np.isfinite(y).all(-1)
    qb = y.shape[1]
    # ‖y‖² = 2 yᵀc + s_b  →  rows [2yᵀ, e_b] · [c; s] = ‖y‖²
    rows = np.zeros(seen.shape + (3 + qb,))
    rows[..., :3] = 2 * np.where(seen[..., None], y, 0.0)
    rows[..., 3:] = np.eye(qb)[None] * seen[..., None]
    rhs = np.where(seen, (np.where(seen[..., None], y, 0.0) ** 2).sum(-1), 0.0)
    sol, *_ = np.linalg.lstsq(rows.reshape(-1, 3 + qb), rhs.ravel(), rcond=1e-10)
    c = sol[:3]
    p = np.einsum("nij,j->ni", R, c) + t
    p[~ok] = np.nan  # the caller fills frames without a pose of A
    return p


def start_points(ma: np.ndarray, mb: np.ndarray, frames: np.ndarray, poses=None) -> tuple[np.ndarray, np.ndarray]:
    """(F, 3) where Kirk's fit of groups A (n,qa,3) and B starts on `frames`: the sphere fit of the larger
    group's frame (`sphere_centre_guess`), else (and where it has no pose) the midpoint of their centroids;
    and (F,) bool where the sphere fit placed it."""
    mid = 0.5 * (nanmean(ma[frames], axis=1) + nanmean(mb[frames], axis=1))
    guess = sphere_centre_guess(ma, mb, frames, poses)
    placed = np.zeros(len(frames), dtype=bool) if guess is None else np.isfinite(guess).all(1)
    p = mid if guess is None else np.where(placed[:, None], guess, mid)
    return np.where(np.isfinite(p), p, 0.0), placed


def joint_point(
    markers_a: np.ndarray,
    markers_b: np.ndarray,
    penalty: float = 1e-5,
    frames: np.ndarray | None = None,
    init: np.ndarray | None = None,
    max_iter: int = 60,
    extend: bool = False,
    poses=None,
) -> JointPoint:
    """Solve the Kirk joint-point problem for groups A (n,qa,3) and B (n,qb,3) on `frames` (default all
    usable frames). `init` (n,3) world points override the built-in guess (sphere fit, else midpoint).
    `extend`: the points (and residuals) of the usable frames outside `frames` too, from the fitted radii.
    `poses`: see `sphere_centre_guess`."""
    M = np.concatenate([markers_a, markers_b], axis=1)
    n, q, _ = M.shape
    use = usable_frames(markers_a, markers_b)
    if frames is not None:
        use = np.intersect1d(use, frames)
    F = len(use)
    out_pts = np.full((n, 3), np.nan)
    out_res = np.full((n, q), np.nan)
    if F < 4:
        return JointPoint(out_pts, np.full(q, np.nan), np.inf, use, out_res)
    Mu = M[use]
    seen = np.isfinite(Mu).all(-1)  # (F, q)
    Mz = np.where(seen[..., None], Mu, 0.0)
    if init is not None and np.isfinite(init[use]).all():
        p0 = init[use]
    else:
        p0 = start_points(markers_a, markers_b, use, poses)[0]
    dist0 = np.linalg.norm(Mz - p0[:, None], axis=-1)
    r0 = (np.where(seen, dist0, 0).sum(0) / np.maximum(seen.sum(0), 1)).clip(1e-3)
    p, r = solve_joint_point(Mz, seen, p0, r0, penalty * F, max_iter)
    d = np.linalg.norm(Mz - p[:, None], axis=-1)
    res = np.where(seen, d - r[None], np.nan)
    rms = float(np.sqrt(np.nanmean(res**2)))
    out_pts[use] = p
    out_res[use] = res
    if extend and frames is not None:
        # The other usable frames get their points from the fitted radii: each frame alone is a
        # 3-unknown least-squares problem, started from the nearest fitted frame's point.
        rest = np.setdiff1d(usable_frames(markers_a, markers_b), use)
        if len(rest):
            near = use[np.clip(np.searchsorted(use, rest), 0, len(use) - 1)]
            pts, rres = points_for_radii(M[rest], r, out_pts[near])
            out_pts[rest], out_res[rest] = pts, rres
    return JointPoint(out_pts, r, rms, use, out_res)


def points_for_radii(M: np.ndarray, r: np.ndarray, p0: np.ndarray, iterations: int = 4):
    """Per-frame points (f, 3) keeping distances r (q,) to the markers M (f, q, 3) (NaN: unseen), by
    damped Gauss–Newton from p0; returns (points, residuals (f, q) ‖m − p‖ − r, NaN where unseen)."""
    seen = np.isfinite(M).all(-1)
    Mz = np.where(seen[..., None], M, 0.0)
    w = seen.astype(float)
    p = np.where(np.isfinite(p0), p0, (Mz * w[..., None]).sum(1) / np.maximum(w.sum(1), 1)[:, None])
    for _ in range(iterations):
        diff = Mz - p[:, None]
        d = np.maximum(np.linalg.norm(diff, axis=-1), 1e-12)
        u = diff / d[..., None] * w[..., None]
        e = w * (d - r[None])
        U = u.transpose(0, 2, 1) @ u
        damp = 1e-6 * np.trace(U, axis1=1, axis2=2) / 3 + 1e-15
        p = p + (inv3(U + damp[:, None, None] * np.eye(3)) @ (u.transpose(0, 2, 1) @ e[..., None]))[..., 0]
    d = np.linalg.norm(Mz - p[:, None], axis=-1)
    return p, np.where(seen, d - r[None], np.nan)


@dataclass(frozen=True)
class Tree:
    parent: np.ndarray  # (G,) parent group, −1 at the root
    root: int
    cost: np.ndarray  # (G, G) pair residual rms (m); inf where a pair could not be fitted
    order: list[int]  # root first, parents before children


def pair_costs(markers: np.ndarray, groups: list[np.ndarray], frames: np.ndarray, penalty: float = 1e-5) -> np.ndarray:
    """(G, G) rms of the joint-point fit of every pair of groups on the given (sub-sampled) frames."""
    G = len(groups)
    cost = np.full((G, G), np.inf)
    for a in range(G):
        for b in range(a + 1, G):
            fit = joint_point(markers[:, groups[a]], markers[:, groups[b]], penalty=penalty, frames=frames, max_iter=15)
            cost[a, b] = cost[b, a] = fit.rms
    return cost


def central_root(adjacency: np.ndarray) -> int:
    """The group whose removal splits the tree most evenly (smallest largest remaining part)."""
    import scipy.sparse as sp  # here, not at the top: csgraph's import costs ~0.3 s of a small take
    from scipy.sparse.csgraph import connected_components

    G = len(adjacency)
    best, best_size = 0, G + 1
    for g in range(G):
        keep = np.ones(G, dtype=bool)
        keep[g] = False
        sub = adjacency[np.ix_(keep, keep)]
        _, lab = connected_components(sp.csr_matrix(sub), directed=False)
        largest = np.bincount(lab).max() if len(lab) else 0
        if largest < best_size:
            best, best_size = g, largest
    return best


def spanning_tree(cost: np.ndarray, root: int | None = None) -> Tree:
    """Minimum spanning tree over the pair residuals, rooted at `root` (default: the central group).

    Weights are residual ranks + 1 so that an exact fit (residual 0) is still an edge to csgraph.
    """
    import scipy.sparse as sp
    from scipy.sparse.csgraph import minimum_spanning_tree

    G = len(cost)
    if G == 1:
        return Tree(np.array([-1]), 0, cost, [0])
    iu = np.triu_indices(G, 1)
    vals = cost[iu]
    finite = np.isfinite(vals)
    ranks = np.empty(len(vals))
    ranks[np.argsort(np.where(finite, vals, np.inf), kind="stable")] = np.arange(1, len(vals) + 1)
    W = np.zeros((G, G))
    W[iu] = np.where(finite, ranks, 0.0)  # an unfittable pair is no edge
    mst = minimum_spanning_tree(sp.csr_matrix(W)).toarray()
    adj = (mst + mst.T) > 0
    if root is None:
        root = central_root(adj)
    parent = np.full(G, -1)
    order = [root]
    seen = {root}
    frontier = [root]
    while frontier:
        nxt = []
        for g in frontier:
            for h in np.flatnonzero(adj[g]):
                if h not in seen:
                    parent[h] = g
                    seen.add(int(h))
                    order.append(int(h))
                    nxt.append(int(h))
        frontier = nxt
    return Tree(parent, int(root), cost, order)


def inv3(A: np.ndarray) -> np.ndarray:
    """Inverses of symmetric (F, 3, 3) matrices by the adjugate, written out: the batched LAPACK inverse
    (and np.cross) cost more in per-call overhead than the arithmetic (the LM step inverts every frame's
    block at each try)."""
    a, b, c = A[:, 0, 0], A[:, 0, 1], A[:, 0, 2]
    d, e, f = A[:, 1, 1], A[:, 1, 2], A[:, 2, 2]
    c00, c01, c02 = d * f - e * e, c * e - b * f, b * e - c * d
    c11, c12, c22 = a * f - c * c, b * c - a * e, a * d - b * b
    det = a * c00 + b * c01 + c * c02
    out = np.empty_like(A)
    out[:, 0, 0], out[:, 1, 1], out[:, 2, 2] = c00, c11, c22
    out[:, 0, 1] = out[:, 1, 0] = c01
    out[:, 0, 2] = out[:, 2, 0] = c02
    out[:, 1, 2] = out[:, 2, 1] = c12
    return out / det[:, None, None]


def solve_joint_point(M: np.ndarray, seen: np.ndarray, p0: np.ndarray, r0: np.ndarray, lam: float, max_iter: int = 60, tol: float = 1e-9):
    """Levenberg–Marquardt on Σ_(f,a seen) (‖M_fa − p_f‖ − r_a)² + lam Σ_a r_a², frames eliminated by a
    Schur complement. M (F,q,3) with unseen entries zeroed, seen (F,q); returns (p (F,3), r (q,))."""
    p, r = solve_joint_points(M[None], seen[None], p0[None], r0[None], np.array([lam], dtype=float), max_iter, tol)
    return p[0], r[0]


def solve_joint_points(M: np.ndarray, seen: np.ndarray, p0: np.ndarray, r0: np.ndarray, lam: np.ndarray,
                       max_iter: int = 60, tol: float = 1e-9):
    """`solve_joint_point` for B independent problems at once, each with its own damping and stopping (a step
    that does not lower a problem's cost is retried with more damping; the problems still running are stepped
    together): M (B,F,q,3), seen (B,F,q), p0 (B,F,3), r0 (B,q), lam (B,); returns (p (B,F,3), r (B,q)). A
    marker column a problem never sees (padding) keeps its starting radius."""
    w = seen.astype(float)
    B, F, q = w.shape
    eye3 = np.eye(3)
    never = w.sum(1) == 0  # (B, q)

    def residual(i, p, r):
        diff = M[i] - p[:, :, None]
        d = np.sqrt(np.einsum("bfqi,bfqi->bfq", diff, diff))
        return w[i] * (d - r[:, None]), diff, np.maximum(d, 1e-12)

    def cost_of(i, e, r):
        return (e**2).sum((1, 2)) + lam[i] * (r**2).sum(1)

    p, r = p0.astype(float).copy(), r0.astype(float).copy()
    every = np.arange(B)
    e, diff, d = residual(every, p, r)
    cost = cost_of(every, e, r)
    mu = np.full(B, 1e-3)
    steps = np.zeros(B, dtype=int)
    done = np.full(B, max_iter <= 0)
    while not done.all():
        i = np.flatnonzero(~done)
        n = len(i)
        wi = w[i]
        u = diff[i] / d[i][..., None] * wi[..., None]  # (n,F,q,3) = −∂e/∂p; ∂e/∂r = −1: the p–r block of JᵀJ is uᵀ
        # Contiguous copies: numpy's stacked matmul on transposed views is several times slower.
        ut = np.ascontiguousarray(u.swapaxes(2, 3))
        U = ut @ u  # (n,F,3,3)
        V = wi.sum(1) + lam[i, None] + never[i]
        gp = (ut @ e[i][..., None])[..., 0]  # −∂cost/∂p / 2
        gr = -(e[i].sum(1)) + lam[i, None] * r[i]
        diagU = (U[..., 0, 0] + U[..., 1, 1] + U[..., 2, 2]) / 3
        damp = (mu[i, None] * np.maximum(diagU, 1e-12) + 1e-15)[..., None, None] * eye3
        Ui = inv3((U + damp).reshape(n * F, 3, 3)).reshape(n, F, 3, 3)
        UiW = (Ui @ ut).reshape(n, 3 * F, q)
        u_rows = np.ascontiguousarray(u.transpose(0, 2, 1, 3)).reshape(n, q, 3 * F)  # Σ_f as one BLAS product
        S = V[..., None] * (1 + mu[i, None, None]) * np.eye(q) - u_rows @ UiW
        rhs = -gr - (u_rows @ (Ui @ gp[..., None]).reshape(n, 3 * F, 1))[..., 0]
        try:
            dr = np.linalg.solve(S, rhs[..., None])[..., 0]
        except np.linalg.LinAlgError:
            dr = np.stack([np.linalg.lstsq(S[b], rhs[b], rcond=None)[0] for b in range(n)])
        dp = (Ui @ (gp - (ut @ dr[:, None, :, None])[..., 0])[..., None])[..., 0]
        p_new, r_new = p[i] + dp, r[i] + dr
        e_new, diff_new, d_new = residual(i, p_new, r_new)
        c_new = cost_of(i, e_new, r_new)
        ok = c_new <= cost[i]
        b = i[ok]
        gain = cost[b] - c_new[ok]
        p[b], r[b], e[b], diff[b], d[b], cost[b] = p_new[ok], r_new[ok], e_new[ok], diff_new[ok], d_new[ok], c_new[ok]
        mu[i] = np.where(ok, np.maximum(mu[i] / 10, 1e-9), mu[i] * 10)
        steps[b] += 1
        done[b[gain <= tol * np.maximum(cost[b], 1e-30)]] = True
        done |= (mu > 1e10) | (steps >= max_iter)
    return p, r
