"""`fit_markers` on the simulator's walk and kiosk routines with soft tissue (issue 31's figures): bodies
found, markers on the right body, the tree, bone lengths, time. Prints a table, asserts nothing.

Each case: the simulated human (16 bodies), 2–4 skin markers a body, 30 s at 144 Hz, 1 mm noise, 3.6 %
occlusion gaps, one label swap, soft tissue `--sta` mm (simulator/soft_tissue.py's rule). "markers right":
each found body is matched to the true body most of its markers ride (one to one, largest overlap first);
a marker is right when its found body is matched to its own. Bones are compared where the found tree has
the true joints at both ends. "fresh s" (with `--fresh`) is `flockcal fit-markers --json` on the take
saved as a marker .npz, in a new interpreter, start-up included (issue 31: ≤ 3 s for 46 markers × 30 s).

    python benchmarks/bench_optical_sim.py                       # walk and kiosk, seeds 0-5, 8 mm
    python benchmarks/bench_optical_sim.py --seeds 0 1 --sta 12 --fresh
    python benchmarks/bench_optical_sim.py --routines walk --seeds 1 --per-body 3 4 --joint-bias   # and --sta 0

`flockcal simulate -o take.c3d`'s marker take (docs/simulator.md), seeds 1-5:

    python benchmarks/bench_optical_sim.py --routines walk --seeds 1 2 3 4 5 --sta 0 --seconds 45 --rate 100 \
        --per-body 3 4 --occlusion 0 --swaps 0

`--joint-bias` also prints, per case, how far each tree joint's reported centre (`fit.joint_points`) sits
from the simulator's true joint centre (the child bone's origin): the constant offset (median over frames,
in the true bone's frame) and the scatter about it; median and range over the true joints found. With
`--per-joint`, one line a joint: its kind, the route that placed it, the offset and (a hinge) its part
across the axis, and the residual rms of plain least squares over the two bodies' marker-only poses at
its own centre and at the true one (the true centre's mean in each body's pose frame).

`--floor` prints what the skin alone leaves (3 or more markers a body): each body's markers with their
soft-tissue slide but no noise, gaps or swaps, fitted rigidly to their rest layout in the bone frame (the
pose the best possible marker fit gives), and every true joint placed by plain least squares over those
poses (a hinge given its true point along the axis): centres' offsets from the truth, and the bones.

    python benchmarks/bench_optical_sim.py --per-body 3 4 --seeds 0 1 2 --floor

`--segmentation` runs the segmentation alone (a fraction of a second a take): the bodies and markers
columns, and each found body that mixes true bodies or misses some of its own, marker by marker; what the
segmentation rules are tried on first.

    python benchmarks/bench_optical_sim.py --segmentation
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def adjusted_rand(a: np.ndarray, b: np.ndarray) -> float:
    """Adjusted Rand index of two labelings (1: the same partition)."""
    from math import comb

    _, ia = np.unique(a, return_inverse=True)
    _, ib = np.unique(b, return_inverse=True)
    table = np.zeros((ia.max() + 1, ib.max() + 1), dtype=int)
    np.add.at(table, (ia, ib), 1)
    pairs = sum(comb(int(x), 2) for x in table.ravel())
    ra = sum(comb(int(x), 2) for x in table.sum(1))
    rb = sum(comb(int(x), 2) for x in table.sum(0))
    expected = ra * rb / comb(len(a), 2)
    top = (ra + rb) / 2
    return 1.0 if top == expected else (pairs - expected) / (top - expected)


def matched(found: dict[str, list[str]], marker_body: dict[str, str]) -> dict[str, str]:
    """Found body → true body, one to one, largest overlap first."""
    overlap = sorted(((sum(marker_body[m] == t for m in ms), f, t) for f, ms in found.items()
                      for t in set(marker_body.values())), reverse=True)
    out, used = {}, set()
    for count, f, t in overlap:
        if count and f not in out and t not in used:
            out[f] = t
            used.add(t)
    return out


def score(out: dict, truth: dict) -> dict:
    """The issue's figures for one fit's JSON against the simulator's truth."""
    mb = truth["marker_body"]
    names = [m for ms in out["bodies"].values() for m in ms]
    to_true = matched(out["bodies"], mb)
    found_of = {m: f for f, ms in out["bodies"].items() for m in ms}
    right = sum(to_true.get(found_of[m]) == mb[m] for m in names)
    true_edges = {frozenset(e) for e in truth["parent"].items()}
    found_edges = {frozenset((to_true.get(c, c), to_true.get(p, p))) for c, p in out["parent"].items()}
    true_bones = {}
    for b in truth["bones"]:
        f, t = b["from_joint"], b["to_joint"]
        true_bones[frozenset([frozenset([f, truth["parent"][f]]), frozenset([t, truth["parent"][t]])])] = b["length_m"]
    errs = []
    par = {to_true.get(c, c): to_true.get(p, p) for c, p in out["parent"].items()}
    for b in out["bones"]:
        f, t = to_true.get(b["from_joint"], b["from_joint"]), to_true.get(b["to_joint"], b["to_joint"])
        if f in par and t in par:
            key = frozenset([frozenset([f, par[f]]), frozenset([t, par[t]])])
            if key in true_bones:
                errs.append(abs(b["length_m"] - true_bones[key]))
    labels_true = np.array([mb[m] for m in names])
    labels_found = np.array([found_of[m] for m in names])
    return {
        "bodies": len(out["bodies"]), "true_bodies": len(set(mb.values())),
        "markers_right": right / len(names), "ari": adjusted_rand(labels_true, labels_found),
        "edges": len(found_edges & true_edges), "true_edges": len(true_edges),
        "wrong_edges": len(found_edges - true_edges),
        "bones": len(errs), "true_bones": len(true_bones),
        "bone_median_mm": 1000 * float(np.median(errs)) if errs else float("nan"),
        "bone_max_mm": 1000 * float(np.max(errs)) if errs else float("nan"),
        "swaps": truth["swaps"], "swap_events": [(e["markers"], round(e["time_s"], 2)) for e in out["swap_events"]],
    }


def simulate(routine: str, seed: int, sta_mm: float, seconds: float, rate_hz: float, per_body=(2, 4),
             occlusion: float = 0.036, swaps: int = 1):
    from flockcal.simulator import optical as so

    return so.simulate_markers("human", routine, seconds=seconds, rate_hz=rate_hz, seed=seed, per_body=tuple(per_body),
                               noise_m=0.001, occlusion=occlusion, n_swaps=swaps, sta_mm=sta_mm)


def joint_bias(fit, truth: dict, routine: str, seed: int, seconds: float, rate_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """(offset, scatter) in metres for each found tree joint that is a true joint: the median over frames
    of the reported centre minus the true one, in the true bone's frame (its norm), and the median
    distance of the per-frame error from that offset."""
    from flockcal.simulator import motion as motion_lib
    from flockcal.simulator.optical import bone_poses, by_name

    model = by_name("human", seed=seed)
    mo = motion_lib.routine(model, routine, seconds, rate_hz, seed)
    L, root_t, _ = mo.pose(mo.times)
    B, b = bone_poses(model, L, root_t)
    names, tp = list(model.names), truth["parent"]
    offset, scatter = [], []
    for c in np.flatnonzero(fit.tree.parent >= 0):
        child, parent = fit.labels[c], fit.labels[fit.tree.parent[c]]
        bone = child if tp.get(child) == parent else parent if tp.get(parent) == child else None
        if bone is None or int(c) not in fit.joint_points:
            continue
        j = names.index(bone)
        e = fit.joint_points[int(c)] - b[:, j]
        ok = np.isfinite(e).all(1)
        local = np.einsum("nji,nj->ni", B[ok, j], e[ok])
        med = np.median(local, axis=0)
        offset.append(float(np.linalg.norm(med)))
        scatter.append(float(np.median(np.linalg.norm(local - med, axis=1))))
    return np.array(offset), np.array(scatter)


def pair_ls(Rc, tc, Rp, tp, ok):
    """Plain least squares of R_c c + t_c = R_p l + t_p over the frames `ok`: (c, l), minimum norm."""
    A = np.concatenate([Rc[ok], -Rp[ok]], axis=2).reshape(-1, 6)
    x, *_ = np.linalg.lstsq(A, (tp[ok] - tc[ok]).reshape(-1), rcond=None)
    return x[:3], x[3:]


def rms_at(Rc, tc, Rp, tp, ok, c, l) -> float:
    e = np.einsum("nij,j->ni", Rc[ok], c) + tc[ok] - np.einsum("nij,j->ni", Rp[ok], l) - tp[ok]
    return float(np.sqrt((e**2).sum(1).mean()))


def per_joint(fit, truth: dict, routine: str, seed: int, seconds: float, rate_hz: float) -> list[str]:
    """One line a found true joint: kind, route, offset (mm; a hinge: across its axis too) and the residual
    of plain least squares over the marker-only poses at its own centre and at the true one."""
    from flockcal.simulator import motion as motion_lib
    from flockcal.simulator.optical import bone_poses, by_name

    model = by_name("human", seed=seed)
    mo = motion_lib.routine(model, routine, seconds, rate_hz, seed)
    L, root_t, _ = mo.pose(mo.times)
    B, b = bone_poses(model, L, root_t)
    names, mb, ex = list(model.names), truth["marker_body"], fit.exercised
    true_of = {}
    for g, grp in enumerate(fit.groups):
        bodies = [mb[fit.marker_names[i]] for i in grp]
        true_of[g] = max(set(bodies), key=bodies.count)
    lines = []
    for c in np.flatnonzero(fit.tree.parent >= 0):
        p = int(fit.tree.parent[c])
        child, parent = (c, p) if truth["parent"].get(true_of[c]) == true_of[p] else (p, c)
        if truth["parent"].get(true_of[child]) != true_of[parent] or int(c) not in fit.joint_points:
            continue
        j = names.index(true_of[child])
        e = fit.joint_points[int(c)] - b[:, j]
        ok = np.isfinite(e).all(1)
        off = np.median(np.einsum("nji,nj->ni", B[ok, j], e[ok]), axis=0)
        across = off
        if model.joint_type[j] == "hinge":
            ax = model.hinge_axis[j] / np.linalg.norm(model.hinge_axis[j])
            across = off - (off @ ax) * ax
        route = "pair fit" if c in fit.pair_route else "point" if c in fit.point_route else "Kirk"
        res = "   -      -"
        if ex.framed[child] and ex.framed[parent]:
            Rc, tc, Rp, tp = ex.rotations[:, child], ex.positions[:, child], ex.rotations[:, parent], ex.positions[:, parent]
            v = ex.valid[:, child] & ex.valid[:, parent]
            cc, ll = pair_ls(Rc, tc, Rp, tp, v)
            xc = np.einsum("nji,nj->ni", Rc[v], b[v, j] - tc[v]).mean(0)
            xp = np.einsum("nji,nj->ni", Rp[v], b[v, j] - tp[v]).mean(0)
            res = f"{1000 * rms_at(Rc, tc, Rp, tp, v, cc, ll):6.1f} {1000 * rms_at(Rc, tc, Rp, tp, v, xc, xp):6.1f}"
        lines.append(f"          {names[j]:<12} {model.joint_type[j]:<5} {route:<8} offset {1000 * np.linalg.norm(off):5.1f} "
                     f"across {1000 * np.linalg.norm(across):5.1f} mm  residual at least squares / truth {res} mm")
    return lines


def floor(routine: str, seed: int, sta_mm: float, seconds: float, rate_hz: float, per_body) -> tuple[np.ndarray, np.ndarray]:
    """(centre offsets, bone errors) in metres from the skin alone (module docstring, `--floor`)."""
    from flockcal.simulator import motion as motion_lib
    from flockcal.simulator import optical as so
    from flockcal.simulator.soft_tissue import SoftTissue
    from flockcal.solver.optical.rigid import rigid_fit

    model = so.by_name("human", seed=seed)
    mo = motion_lib.routine(model, routine, seconds, rate_hz, seed)
    L, root_t, q = mo.pose(mo.times)
    B, b = so.bone_poses(model, L, root_t)
    body, offsets, _ = so.place_markers(model, tuple(per_body), seed)
    slid = offsets[None].repeat(len(q), 0)
    if sta_mm > 0:
        sta = SoftTissue.for_sites(model, body, so.skin_normals(model, body, offsets), sta_mm, seed, stream=0x0A57)
        slid = slid + sta.slides(q)
    R, t = {}, {}
    for i in range(model.m):
        k = np.flatnonzero(body == i)
        E, e, _ = rigid_fit(offsets[k], slid[:, k])  # the markers' rest layout → where the skin put them
        R[i], t[i] = B[:, i] @ E, np.einsum("nij,nj->ni", B[:, i], e) + b[:, i]
    centre, offs = {}, []
    every = np.ones(len(q), dtype=bool)
    for j in range(model.m):
        p = model.parent[j]
        if p < 0:
            continue
        c, l = pair_ls(R[j], t[j], R[p], t[p], every)
        l = l - model.joint_offset[j]
        if model.joint_type[j] == "hinge":
            ax = model.hinge_axis[j] / np.linalg.norm(model.hinge_axis[j])
            c, l = c - (c @ ax) * ax, l - (l @ ax) * ax
        centre[j] = (c, l + model.joint_offset[j])
        offs.append(float(np.linalg.norm(c)))
    errs = []
    for bone in model.truth()["bones"]:
        x = model.names.index(bone["body"])
        a, z = (model.names.index(bone[key]) for key in ("from_joint", "to_joint"))
        pa, pz = (centre[j][0] if j == x else centre[j][1] for j in (a, z))
        errs.append(abs(float(np.linalg.norm(pa - pz)) - bone["length_m"]))
    return np.array(offs), np.array(errs)


def segmentation_lines(take, truth: dict) -> tuple[str, list[str]]:
    """`segment_markers` alone on the take (the markers `fit_markers` keeps: seen in 20 % of the frames or
    more): the figures of the table's "bodies" and "markers" columns, its time, and one line for each found
    body that holds markers of more than one true body or not all of its own (each marker with its true body)."""
    from flockcal.solver.optical.segmentation import segment_markers

    keep = np.flatnonzero(np.isfinite(take.markers).all(-1).mean(0) >= 0.2)
    names = [take.marker_names[i] for i in keep]
    t0 = time.perf_counter()
    seg = segment_markers(take.markers[:, keep])
    wall = time.perf_counter() - t0
    mb = truth["marker_body"]
    found = {f"body{g}": [names[i] for i in grp] for g, grp in enumerate(seg.groups)}
    to_true = matched(found, mb)
    right = sum(to_true.get(f) == mb[m] for f, ms in found.items() for m in ms)
    head = f"{len(found):>3}/{len(set(mb.values())):<3} {right / len(names):7.3f} {wall:6.2f}"
    lines = []
    for f, ms in found.items():
        own = to_true.get(f)
        if any(mb[m] != own for m in ms) or sum(mb[m] == own for m in names) != len(ms):
            lines.append(f"        {f} ({own or 'no true body'}): " + ", ".join(f"{m} ({mb[m]})" for m in ms))
    return head, lines


def fresh_wall(take, tmp: Path) -> float:
    """Wall time of `flockcal fit-markers --json` on the take in a new interpreter."""
    from flockcal.markers import save_markers

    path = tmp / "take.npz"
    save_markers(path, take)
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "flockcal", "fit-markers", str(path), "--json"],
                          capture_output=True, text=True, check=False)  # fmt: skip
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        sys.exit(f"fit-markers failed: {proc.stderr.strip()}")
    return wall


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--routines", nargs="+", default=["walk", "kiosk"])
    ap.add_argument("--seeds", nargs="+", type=int, default=list(range(6)))
    ap.add_argument("--sta", type=float, default=8.0, help="soft tissue, mm (default 8)")
    ap.add_argument("--seconds", type=float, default=30.0)
    ap.add_argument("--rate", type=float, default=144.0)
    ap.add_argument("--per-body", nargs=2, type=int, default=[2, 4], metavar=("LOW", "HIGH"),
                    help="markers a body (default 2 4)")
    ap.add_argument("--occlusion", type=float, default=0.036, help="fraction of frames in gaps (default 0.036)")
    ap.add_argument("--swaps", type=int, default=1, help="label swaps (default 1)")
    ap.add_argument("--fresh", action="store_true", help="also time a fresh `flockcal fit-markers` process")
    ap.add_argument("--verbose", action="store_true", help="print the swaps and the wrong edges")
    ap.add_argument("--joint-bias", action="store_true", help="print the joint centres' offset from the truth")
    ap.add_argument("--per-joint", action="store_true", help="with --joint-bias: a line a joint")
    ap.add_argument("--floor", action="store_true", help="print what the skin alone leaves (3+ markers a body)")
    ap.add_argument("--segmentation", action="store_true",
                    help="run the segmentation alone: bodies, markers right, its time, and the bodies it got wrong")
    args = ap.parse_args()
    from flockcal.solver.optical.pipeline import fit_markers

    if args.segmentation:
        print(f"{'routine':<7} {'seed':>4} {'k':>3} {'bodies':>7} {'markers':>7} {'seg s':>6}")
        for routine in args.routines:
            for seed in args.seeds:
                take, truth = simulate(routine, seed, args.sta, args.seconds, args.rate, args.per_body, args.occlusion, args.swaps)
                head, lines = segmentation_lines(take, truth)
                print(f"{routine:<7} {seed:>4} {take.markers.shape[1]:>3} {head}")
                print("\n".join(lines)) if lines else None
        return 0

    print(f"load average before: {' '.join(f'{x:.1f}' for x in os.getloadavg())}  (cores: {os.cpu_count()})")
    print(f"{'routine':<7} {'seed':>4} {'k':>3} {'bodies':>7} {'markers':>7} {'ARI':>6} {'edges':>6} {'wrong':>5} "
          f"{'bones':>6} {'med mm':>6} {'max mm':>6} {'fit s':>6} {'fresh s':>7}")
    with tempfile.TemporaryDirectory() as tmp:
        for routine in args.routines:
            for seed in args.seeds:
                take, truth = simulate(routine, seed, args.sta, args.seconds, args.rate, args.per_body, args.occlusion, args.swaps)
                t0 = time.perf_counter()
                fit = fit_markers(take.markers, take.marker_names, take.rate_hz, take.times)
                out = fit.to_dict()
                wall = time.perf_counter() - t0
                s = score(out, truth)
                fresh = f"{fresh_wall(take, Path(tmp)):7.2f}" if args.fresh else f"{'-':>7}"
                print(f"{routine:<7} {seed:>4} {take.markers.shape[1]:>3} {s['bodies']:>3}/{s['true_bodies']:<3} "
                      f"{s['markers_right']:7.3f} {s['ari']:6.3f} {s['edges']:>3}/{s['true_edges']:<2} {s['wrong_edges']:>5} "
                      f"{s['bones']:>3}/{s['true_bones']:<2} {s['bone_median_mm']:6.1f} {s['bone_max_mm']:6.1f} "
                      f"{wall:6.2f} {fresh}")
                if args.verbose:
                    print(f"        swaps {s['swaps']} found {s['swap_events']}")
                if args.joint_bias:
                    off, sc = joint_bias(fit, truth, routine, seed, args.seconds, args.rate)
                    if off.size:
                        print(f"        joint centres: offset median {1000 * np.median(off):.1f} mm "
                              f"({1000 * off.min():.1f}-{1000 * off.max():.1f}) over {off.size} joints; "
                              f"scatter about it {1000 * sc.min():.1f}-{1000 * sc.max():.1f} mm")
                    if args.per_joint:
                        print("\n".join(per_joint(fit, truth, routine, seed, args.seconds, args.rate)))
                if args.floor:
                    off, err = floor(routine, seed, args.sta, args.seconds, args.rate, args.per_body)
                    print(f"        skin alone: centres {1000 * np.median(off):.1f} mm median ({1000 * off.min():.1f}-"
                          f"{1000 * off.max():.1f}); bones {1000 * np.median(err):.1f} median, {1000 * err.max():.1f} worst, "
                          f"{int((err > 0.005).sum())}/{err.size} over 5 mm")
    print(f"load average after: {' '.join(f'{x:.1f}' for x in os.getloadavg())}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
