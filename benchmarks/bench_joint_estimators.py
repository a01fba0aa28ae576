"""Joint centres under simulated soft tissue by other estimators than the fit's, against the simulator's
truth (issue 31 item 3: can an estimator remove the centres' offset?). Prints a table, asserts nothing.

Each body's markers are its true ones (no segmentation), 3–4 a body, 1 mm noise, 3.6 % occlusion, no swap.
Per true joint, the offset of the centre from the truth (median over frames, in the true bone's frame; a
hinge: across its axis only, its point along the axis being a rule's) by:
- plain: pair least squares over the bodies' marker-only poses (generalised Procrustes + Kabsch);
- weighted: the poses by Kabsch with each marker weighted by 1 / its own scatter about the body's shape;
- least3: the poses from the three markers of a body that scatter least;
- frames: plain, with frames reweighted by their joint residual (Cauchy, 5 rounds);
- kirk: Kirk's per-frame point (the joint fit's, on 1000 frames).

    python benchmarks/bench_joint_estimators.py walk:1 kiosk:0          # routine:seed, 8 mm of soft tissue
    python benchmarks/bench_joint_estimators.py walk:1 --sta 0
"""

from __future__ import annotations

import argparse

import numpy as np

METHODS = ("plain", "weighted", "least3", "frames", "kirk")


def weighted_fit(ref: np.ndarray, obs: np.ndarray, w: np.ndarray):
    """Kabsch of ref (q, 3) onto obs (n, q, 3) with marker weights w (q,); NaN markers carry none."""
    seen = np.isfinite(obs).all(-1)
    W = seen * w[None]
    X = np.where(seen[..., None], obs, 0.0)
    s = W.sum(1, keepdims=True)
    xc = (W[..., None] * X).sum(1) / s
    pc = (W[..., None] * ref[None]).sum(1) / s
    H = ((ref[None] - pc[:, None]) * W[..., None]).transpose(0, 2, 1) @ (X - xc[:, None])
    U, _, Vt = np.linalg.svd(H)
    D = np.ones((len(obs), 3))
    D[:, 2] = np.sign(np.linalg.det(U @ Vt))
    R = (Vt.transpose(0, 2, 1) * D[:, None, :]) @ U.transpose(0, 2, 1)
    return R, xc - (R @ pc[..., None])[..., 0], seen.sum(1) >= 3


def pair_ls(Rc, tc, Rp, tp, ok, w=None):
    A = np.concatenate([Rc[ok], -Rp[ok]], axis=2)
    y = tp[ok] - tc[ok]
    if w is not None:
        A, y = A * np.sqrt(w)[:, None, None], y * np.sqrt(w)[:, None]
    x, *_ = np.linalg.lstsq(A.reshape(-1, 6), y.reshape(-1), rcond=None)
    return x[:3], x[3:]


def point(R, t, c):
    return np.einsum("nij,j->ni", R, c) + t


def run(routine: str, seed: int, sta_mm: float, seconds: float = 30.0, rate_hz: float = 144.0) -> list[dict]:
    from flockcal.simulator import motion as motion_lib
    from flockcal.simulator import optical as so
    from flockcal.solver.optical.joints import joint_point
    from flockcal.solver.optical.rigid import apply, procrustes_mean

    take, truth = so.simulate_markers("human", routine, seconds=seconds, rate_hz=rate_hz, seed=seed, per_body=(3, 4),
                                      noise_m=0.001, occlusion=0.036, n_swaps=0, sta_mm=sta_mm)
    model = so.by_name("human", seed=seed)
    mo = motion_lib.routine(model, routine, seconds, rate_hz, seed)
    L, root_t, _ = mo.pose(mo.times)
    B, b = so.bone_poses(model, L, root_t)
    body = np.array([model.names.index(truth["marker_body"][nm]) for nm in take.marker_names])
    M = take.markers
    poses = {}
    for i in range(model.m):
        idx = np.flatnonzero(body == i)
        shape, R, t, ok = procrustes_mean(M[:, idx])
        sd = np.sqrt(np.nanmean(np.linalg.norm(apply(R, t, shape) - M[:, idx], axis=-1) ** 2, axis=0))
        keep = idx[np.argsort(sd)[:3]]
        poses[i] = {"plain": (R, t, ok), "weighted": weighted_fit(shape, M[:, idx], 1 / sd**2),
                    "least3": procrustes_mean(M[:, keep])[1:], "idx": idx}

    def offset(pts, j, axis):
        ok = np.isfinite(pts).all(1)
        off = np.median(np.einsum("nji,nj->ni", B[ok, j], pts[ok] - b[ok, j]), axis=0)
        return 1000 * float(np.linalg.norm(off if axis is None else off - (off @ axis) * axis))

    rows = []
    for j in range(model.m):
        p = model.parent[j]
        if p < 0:
            continue
        axis = model.hinge_axis[j] / np.linalg.norm(model.hinge_axis[j]) if model.joint_type[j] == "hinge" else None
        row = {"joint": model.names[j], "kind": model.joint_type[j]}
        for name in ("plain", "weighted", "least3"):
            (Rc, tc, okc), (Rp, tp, okp) = poses[j][name], poses[p][name]
            ok = okc & okp
            c, l = pair_ls(Rc, tc, Rp, tp, ok)
            if name == "plain":  # and again with frames reweighted by their residual
                cf, lf = c, l
                for _ in range(5):
                    r = np.linalg.norm(point(Rc[ok], tc[ok], cf) - point(Rp[ok], tp[ok], lf), axis=1)
                    cf, lf = pair_ls(Rc, tc, Rp, tp, ok, 1 / (1 + (r / (1.4826 * np.median(r))) ** 2))
                pts = 0.5 * (point(Rc, tc, cf) + point(Rp, tp, lf))
                pts[~ok] = np.nan
                row["frames"] = offset(pts, j, axis)
            pts = 0.5 * (point(Rc, tc, c) + point(Rp, tp, l))
            pts[~ok] = np.nan
            row[name] = offset(pts, j, axis)
        frames = np.linspace(0, len(M) - 1, 1000).astype(int)
        row["kirk"] = offset(joint_point(M[:, poses[j]["idx"]], M[:, poses[p]["idx"]], frames=frames, extend=True).points, j, axis)
        rows.append(row)
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("cases", nargs="+", help="routine:seed")
    ap.add_argument("--sta", type=float, default=8.0, help="soft tissue, mm (default 8)")
    args = ap.parse_args()
    every = []
    for case in args.cases:
        routine, seed = case.split(":")
        rows = run(routine, int(seed), args.sta)
        every += rows
        print(f"{case} (soft tissue {args.sta:g} mm): offset from the true centre, mm")
        print(f"  {'joint':<12} {'kind':<6}" + "".join(f"{m:>9}" for m in METHODS))
        for r in rows:
            print(f"  {r['joint']:<12} {r['kind']:<6}" + "".join(f"{r[m]:9.1f}" for m in METHODS))
        print(f"  {'median':<19}" + "".join(f"{np.median([r[m] for r in rows]):9.1f}" for m in METHODS))
    if len(args.cases) > 1:
        print(f"all {len(every)} joints: median" + "".join(f"{np.median([r[m] for r in every]):9.1f}" for m in METHODS))
        print(f"{'':<14}worst " + "".join(f"{np.max([r[m] for r in every]):9.1f}" for m in METHODS))
        print(f"{'':<8}within 5 mm " + "".join(f"{np.mean([r[m] <= 5 for r in every]):9.2f}" for m in METHODS))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
