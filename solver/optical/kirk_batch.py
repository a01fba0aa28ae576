"""Kirk's joint-point fit (joints.py) of many pairs of bodies at once, in one padded batch: the costs of every
pair for the tree, and the points of a tree's joints on every frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flockcal.solver.optical.joints import points_for_radii, solve_joint_points, start_points
from flockcal.solver.optical.rigid import procrustes_mean


def padded_pairs(markers: np.ndarray, columns: list[np.ndarray], frames: np.ndarray):
    """(B, F, Q, 3) the markers `columns` of each problem on `frames`, zero where unseen (padding: never seen),
    and seen (B, F, Q)."""
    Q = max(len(c) for c in columns)
    k = markers.shape[1]
    padded = np.stack([np.concatenate([c, np.full(Q - len(c), k)]) for c in columns]).astype(int)
    Mx = np.concatenate([markers[frames], np.full((len(frames), 1, 3), np.nan)], axis=1)[:, padded]  # (F, B, Q, 3)
    Mx = Mx.transpose(1, 0, 2, 3)
    seen = np.isfinite(Mx).all(-1)
    return np.where(seen[..., None], Mx, 0.0), seen


def shared_poses():
    """`poses` for `joints.sphere_centre_guess`: one body's pose on given frames, computed once for all its pairs."""
    cache: dict = {}

    def poses(points):
        key = points.shape, hash(points.tobytes())
        if key not in cache:
            cache[key] = procrustes_mean(points)[1:]
        return cache[key]

    return poses


def fitted(markers, groups, pairs, frames, penalty, max_iter, poses=None, tol: float = 1e-9):
    """Kirk's fit of each pair (a, b) of `pairs` on `frames`, all at once: points (B, F, 3), radii (B, Q),
    and the padded markers and seen mask it was fitted to. Where both bodies have a frame, the fit starts
    from each one's sphere fit and keeps the better end; then each frame's point is tried at its mirror
    images across either body's markers (`mirrored`) and the fit run on from the better ones: three markers
    leave every point a mirror image across their plane, and a frame started on the wrong side settles there."""
    columns = [np.concatenate([groups[a], groups[b]]) for a, b in pairs]
    Mz, seen = padded_pairs(markers, columns, frames)
    lam = penalty * seen.any(2).sum(1).astype(float)

    def cost_of(which, p, r):
        e = np.where(seen[which], np.linalg.norm(Mz[which] - p[:, :, None], axis=-1) - r[:, None], 0.0)
        return (e**2).sum((1, 2)) + lam[which] * (r**2).sum(1)

    starts = {}
    for a, b in pairs:
        for x, y in ((a, b), (b, a)):
            starts[x, y] = start_points(markers[:, groups[x]], markers[:, groups[y]], frames, poses)
    # A frame the sphere fit could not place (the framed body short of three markers there, a swap blanked)
    # starts at the bodies' midpoint, centimetres off, and may settle in a wrong place: left out where the
    # fit placed most frames.
    placed = np.stack([starts[a, b][1] for a, b in pairs])
    seen &= np.where(placed.mean(1, keepdims=True) >= 0.5, placed, True)[..., None]
    Mz = np.where(seen[..., None], Mz, 0.0)

    def solve(p0, which):
        dist = np.linalg.norm(Mz[which] - p0[:, :, None], axis=-1)
        r0 = ((dist * seen[which]).sum(1) / np.maximum(seen[which].sum(1), 1)).clip(1e-3)
        p, r = solve_joint_points(Mz[which], seen[which], p0, r0, lam[which], max_iter, tol)
        return p, r, cost_of(which, p, r)

    def better_of(p0, which):
        nonlocal p, r, cost
        p2, r2, cost2 = solve(p0, which)
        better = cost2 < cost[which]
        p[which[better]], r[which[better]], cost[which[better]] = p2[better], r2[better], cost2[better]

    every = np.arange(len(pairs))
    p, r, cost = solve(np.stack([starts[a, b][0] for a, b in pairs]), every)
    sizes = np.array([(len(groups[a]), len(groups[b])) for a, b in pairs]).reshape(-1, 2)
    both = every[(sizes.min(1) >= 3) & (sizes[:, 0] == sizes[:, 1])]
    if len(both):
        better_of(np.stack([starts[b, a][0] for a, b in pairs[both]]), both)
    # Two bodies of two markers have no frame to start from: the joint starts at the middle of each pair of
    # their markers in turn (it lies between the two bodies, near their nearest markers), the best kept.
    few = every[sizes.max(1) < 3]
    for i in range(2):
        for j in range(2):
            if len(few):
                both_seen = (seen[few, :, i] & seen[few, :, 2 + j])[..., None]
                better_of(np.where(both_seen, 0.5 * (Mz[few, :, i] + Mz[few, :, 2 + j]), p[few]), few)
    split = np.array([len(groups[a]) for a, _ in pairs])
    flipped = mirrored(Mz, seen, split, p, r)
    moved = np.flatnonzero((flipped != p).any(axis=(1, 2)))
    if len(moved):
        p[moved], r[moved] = solve_joint_points(Mz[moved], seen[moved], flipped[moved], r[moved], lam[moved], max_iter, tol)
    return p, r, Mz, seen


def mirrored(Mz: np.ndarray, seen: np.ndarray, split: np.ndarray, p: np.ndarray, r: np.ndarray) -> np.ndarray:
    """The points p (B, F, 3), each frame's moved to its mirror image across the plane of either body's seen
    markers (columns before / from `split`), or turned about the line through a body's two seen markers (every
    30°), where that keeps the fitted radii r better: three markers leave a point a mirror image across their
    plane, two a whole circle about their line."""
    Q = seen.shape[2]
    out = p.copy()

    def misfit(x):
        return (np.where(seen, np.linalg.norm(Mz - x[:, :, None], axis=-1) - r[:, None], 0.0) ** 2).sum(2)

    best = misfit(p)

    def keep(x, where):
        nonlocal out, best
        cost = misfit(x)
        take = where & (cost < best)
        out = np.where(take[..., None], x, out)
        best = np.where(take, cost, best)

    for side in (np.arange(Q)[None] < split[:, None], np.arange(Q)[None] >= split[:, None]):
        w = (seen & side[:, None]).astype(float)  # (B, F, Q)
        n = w.sum(2)
        c = (Mz * w[..., None]).sum(2) / np.maximum(n, 1)[..., None]
        d = (Mz - c[:, :, None]) * w[..., None]
        lam, V = np.linalg.eigh(np.einsum("bfqi,bfqj->bfij", d, d))
        normal, line = V[..., 0], V[..., 2]  # the least-spread direction (a plane's normal), the most (a line)
        keep(out - 2.0 * ((out - c) * normal).sum(-1, keepdims=True) * normal, n >= 3)
        x = out - c
        along = (x * line).sum(-1, keepdims=True) * line
        across = x - along
        for angle in np.radians(np.arange(30, 360, 30)):  # Rodrigues about the line, from the best so far
            turned = across * np.cos(angle) + np.cross(line, across) * np.sin(angle)
            keep(c + along + turned, n == 2)
    return out


def pair_rms(markers: np.ndarray, groups: list[np.ndarray], pairs: np.ndarray, frames: np.ndarray,
             penalty: float = 1e-5, max_iter: int = 30, tol: float = 1e-9) -> np.ndarray:
    """(len(pairs),) Kirk's joint-point residual of every pair of bodies (a, b) on `frames`, all fitted at
    once (`joints.solve_joint_points`), each started as `joints.joint_point` starts: the rms of the distances'
    residuals (swapped labels are best blanked first: `marker_noise.blank_off_shape`)."""
    pairs = np.asarray(pairs, dtype=int).reshape(-1, 2)
    if not len(pairs):
        return np.zeros(0)
    p, r, Mz, seen = fitted(markers, groups, pairs, frames, penalty, max_iter, shared_poses(), tol)
    e = np.where(seen, np.linalg.norm(Mz - p[:, :, None], axis=-1) - r[:, None], 0.0)
    # Per degree of freedom: each frame's point takes three distances and each radius one, so a joint's
    # residual is the markers' noise whatever the bodies' marker counts (a body of two markers leaves a
    # point fewer distances to fit than one of four, and a smaller plain rms).
    dof = seen.sum((1, 2)) - 3 * seen.any(2).sum(1) - seen.any(1).sum(1)
    return np.sqrt((e**2).sum((1, 2)) / np.maximum(dof, 1))


# A frame's point carried from the fitted radii counts as unsettled beyond this many times the fit's rms.
UNSETTLED = 5.0


@dataclass(frozen=True)
class JointFits:
    """Kirk's fit of tree joints, by joint (its child body)."""

    points: dict[int, np.ndarray]  # (n, 3) world joint centre per frame, NaN where a frame was not usable
    rms: dict[int, float]  # residual rms on the fitted frames (m)
    residuals: dict[int, np.ndarray]  # (n, q) ‖m − p‖ − r of the joint's markers (child's, then parent's)


def carried(markers: np.ndarray, groups: list[np.ndarray], bodies, points: np.ndarray, rest: np.ndarray) -> np.ndarray:
    """(len(rest), 3) where a joint's point starts on the frames `rest`: its median place in the frame of a
    body of the two with three markers or more (the one with more first, each where it has a pose), from the
    frames already fitted (`points`, NaN elsewhere), carried by that body's pose; the nearest fitted frame's
    point where neither has one. A frame started far off can settle on a point's mirror image across a
    body's markers, or short of the point."""
    from flockcal.solver.optical.rigid import apply, rigid_fit, to_body

    done = np.flatnonzero(np.isfinite(points).all(1))
    start = points[done[np.clip(np.searchsorted(done, rest), 0, len(done) - 1)]] if len(done) else np.zeros((len(rest), 3))
    for g in sorted(bodies, key=lambda b: len(groups[b])):  # the larger body last: it wins where both have a pose
        if len(groups[g]) < 3 or not len(done):
            continue
        shape, R, t, ok = procrustes_mean(markers[done][:, groups[g]])
        if ok.sum() < 3:
            continue
        local = np.median(to_body(R[ok], t[ok], points[done][ok][:, None])[:, 0], axis=0)
        R, t, ok = rigid_fit(shape, markers[rest][:, groups[g]])
        start = np.where(ok[:, None], apply(R, t, local[None])[:, 0], start)
    return start


def tree_joint_points(markers: np.ndarray, groups: list[np.ndarray], parent: np.ndarray, joints, frames: np.ndarray,
                      penalty: float = 1e-5, max_iter: int = 30, tol: float = 1e-6) -> JointFits:
    """Kirk's joint point of each tree joint in `joints` (children), all fitted at once on `frames` and carried
    to every other usable frame from the fitted radii (`joints.points_for_radii`)."""
    from flockcal.solver.optical.joints import usable_frames

    joints = [int(c) for c in joints]
    out = JointFits({}, {}, {})
    if not joints:
        return out
    n = len(markers)
    pairs = np.array([(c, int(parent[c])) for c in joints])
    p, r, Mz, seen = fitted(markers, groups, pairs, frames, penalty, max_iter, shared_poses(), tol)
    for s, c in enumerate(joints):
        M = markers[:, np.concatenate([groups[c], groups[int(parent[c])]])]
        q = M.shape[1]
        use = usable_frames(M[:, : len(groups[c])], M[:, len(groups[c]):])
        pts = np.full((n, 3), np.nan)
        fit_here = np.isin(frames, use) & seen[s].any(1)
        pts[frames[fit_here]] = p[s][fit_here]
        rest = np.setdiff1d(use, frames[fit_here])
        e = np.where(seen[s][fit_here, :q], np.linalg.norm(Mz[s][fit_here, :q] - p[s][fit_here, None], axis=-1) - r[s, :q], np.nan)
        out.rms[c] = float(np.sqrt(np.nanmean(e**2))) if np.isfinite(e).any() else float("inf")
        if len(rest):
            start = carried(markers, groups, (c, int(parent[c])), pts, rest)
            pts[rest], e_rest = points_for_radii(M[rest], r[s, :q], start, iterations=10)
            # A frame whose point keeps its distances far worse than the fitted frames did did not settle.
            pts[rest[np.sqrt(np.nanmean(e_rest**2, axis=1)) > UNSETTLED * out.rms[c]]] = np.nan
        out.points[c], out.residuals[c] = pts, np.linalg.norm(M - pts[:, None], axis=-1) - r[s, :q]
    return out
