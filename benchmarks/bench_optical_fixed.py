"""`fit_markers` on markers fixed to their bones (no soft tissue; issue 50 item 1): the tree and the bones over
the simulator's walk, kiosk and exercise routines and several seeds. Prints a table and the worst case; asserts
nothing. The claim it measures (docs/optical.md): every tree edge right, every bone within 3 mm.

Each case: the simulated human (15 bodies by default, as issue 50 measured; `--birds 16` keeps the abdomen),
2–4 markers a body fixed to the bone, 1 mm noise, 3.6 % occlusion gaps, with and without a label swap (`--swaps 0 1`), 30 s at 100 Hz (`flockcal simulate`'s rate). Bodies, ARI and edges are
scored as bench_optical_sim.py scores them (`score`: found bodies matched to true ones by their markers). Bones
are every distance between two joints of one body (a hip's width too, which the fit's bone list, running
from each body's inboard joint, leaves out), found against true, a joint named by the two bodies it links.

    python benchmarks/bench_optical_fixed.py                     # 3 routines × seeds 0-3 × swaps 0/1
    python benchmarks/bench_optical_fixed.py --seeds 0 1 2 3 4 5 6 7 8 9   # docs/optical.md's figure (60 takes)
    python benchmarks/bench_optical_fixed.py --birds 16 --seeds 0 --swaps 1
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np
from bench_optical_sim import score


def joint_distances(joints_of) -> dict:
    """{(body, {joint, joint}): metres} from {body: [(joint name, offset in the body)]}."""
    out = {}
    for body, joints in joints_of.items():
        for x in range(len(joints)):
            for y in range(x + 1, len(joints)):
                (a, pa), (b, pb) = joints[x], joints[y]
                out[body, frozenset((a, b))] = float(np.linalg.norm(np.subtract(pa, pb)))
    return out


def bone_errors(model, fit) -> dict:
    """{(body, {joint, joint}): |found − true| metres} over the true bones; NaN where the fit lacks one."""
    true = {}
    for i, body in enumerate(model.names):
        true[body] = [(frozenset((body, model.names[k])), model.joint_offset[k]) for k in range(model.m)
                      if model.parent[k] == i]
        if model.parent[i] >= 0:
            true[body].append((frozenset((body, model.names[model.parent[i]])), np.zeros(3)))
    name = {c: frozenset((fit.labels[c], fit.labels[fit.parent[c]])) for c in range(len(fit.labels)) if fit.parent[c] >= 0}
    found = {fit.labels[g]: [(name[j], shape.joint_offsets[x]) for x, j in enumerate(shape.joints)]
             for g, shape in enumerate(fit.shapes)}
    t, f = joint_distances(true), joint_distances(found)
    return {key: abs(f[key] - t[key]) if key in f else float("nan") for key in t}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--routines", nargs="+", default=["walk", "kiosk", "exercise"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2, 3])
    ap.add_argument("--swaps", nargs="+", type=int, default=[0, 1], help="label swaps, one run each (default 0 1)")
    ap.add_argument("--birds", type=int, default=15, help="bodies of the simulated human (default 15)")
    ap.add_argument("--seconds", type=float, default=30.0)
    ap.add_argument("--rate", type=float, default=100.0)
    ap.add_argument("--per-body", nargs=2, type=int, default=[2, 4], metavar=("LOW", "HIGH"))
    ap.add_argument("--occlusion", type=float, default=0.036)
    ap.add_argument("--noise-mm", type=float, default=1.0)
    args = ap.parse_args()
    from flockcal.simulator import optical as so
    from flockcal.simulator.body import by_name
    from flockcal.solver.optical.pipeline import fit_markers

    print(f"load average before: {' '.join(f'{x:.1f}' for x in os.getloadavg())}  (cores: {os.cpu_count()})")
    print(f"{'routine':<8} {'seed':>4} {'swaps':>5} {'k':>3} {'bodies':>7} {'ARI':>6} {'edges':>6} {'bones':>6} "
          f"{'med mm':>6} {'max mm':>6} {'fixed':>5} {'fit s':>6}")
    rows = []
    for routine in args.routines:
        for seed in args.seeds:
            for swaps in args.swaps:
                take_model = by_name("human", seed=seed, birds=args.birds)
                take, truth = so.simulate_markers(
                    take_model, routine, seconds=args.seconds, rate_hz=args.rate,
                    seed=seed, per_body=tuple(args.per_body), noise_m=args.noise_mm / 1000.0,
                    occlusion=args.occlusion, n_swaps=swaps, sta_mm=0.0)
                t0 = time.perf_counter()
                fit = fit_markers(take.markers, take.marker_names, take.rate_hz, take.times)
                wall = time.perf_counter() - t0
                s = score(fit.to_dict(), truth)
                errors = np.array(list(bone_errors(take_model, fit).values()))
                s["bones"], s["true_bones"] = int(np.isfinite(errors).sum()), len(errors)
                s["bone_median_mm"], s["bone_max_mm"] = 1000 * np.nanmedian(errors), 1000 * np.max(errors)
                fixed = "yes" if fit.noise is not None and fit.noise.rigid else "no"
                rows.append((routine, seed, swaps, s))
                print(f"{routine:<8} {seed:>4} {swaps:>5} {take.markers.shape[1]:>3} {s['bodies']:>3}/{s['true_bodies']:<3} "
                      f"{s['ari']:6.3f} {s['edges']:>3}/{s['true_edges']:<2} {s['bones']:>3}/{s['true_bones']:<2} "
                      f"{s['bone_median_mm']:6.1f} {s['bone_max_mm']:6.1f} {fixed:>5} {wall:6.2f}")
    trees = sum(s["edges"] == s["true_edges"] and not s["wrong_edges"] for *_, s in rows)
    worst = max(rows, key=lambda r: np.nan_to_num(r[3]["bone_max_mm"], nan=np.inf))
    within = sum(s["bone_max_mm"] <= 3.0 for *_, s in rows)
    print(f"trees right {trees}/{len(rows)}; every bone within 3 mm {within}/{len(rows)}; worst bone "
          f"{worst[3]['bone_max_mm']:.1f} mm ({worst[0]} seed {worst[1]} swaps {worst[2]})")
    print(f"load average after: {' '.join(f'{x:.1f}' for x in os.getloadavg())}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
