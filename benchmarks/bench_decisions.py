"""How flockcal's joint decisions compare with plain least squares and the truth, take by take.

For simulated takes (several routines, seeds, noise levels, true wrist/ankle hinges) and the real captures'
cluster takes: joints determined (ball / hinge) out of the tree's, the largest distance between a
determined ball joint and plain least squares (SVD, fixed 1.5 % cut-off), and the median and worst truth
error of flockcal's determined joints next to plain least squares' on the same joints. Never run in CI.

    python benchmarks/bench_decisions.py            # all cases (~1 min)
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from plain_lsq import plain_take_fit  # noqa: E402

from flockcal.simulator import body as bodies  # noqa: E402
from flockcal.simulator.take import simulate  # noqa: E402
from flockcal.solver.accumulator import GramAccumulator  # noqa: E402
from flockcal.solver.calibration import calibrate  # noqa: E402


def evaluate(take, truth=None, hierarchy=None):
    acc = GramAccumulator(take.n_sensors).add_poses(take.rotations, take.positions, take.valid)
    res = calibrate(acc, hierarchy=hierarchy, names=take.names).to_dict()
    tj = {j["child"]: j for j in (truth or {}).get("joints", [])}
    ball = hinge = 0
    d_plain, ours, theirs = [], [], []
    for j in res["joints"]:
        if not j["determined"]:
            continue
        hinge += j["hinge"]
        ball += not j["hinge"]
        p = plain_take_fit(take, j["child"], j["parent"])
        c = np.array(j["c"])
        if not j["hinge"] and p.rank == 6:
            d_plain.append(np.linalg.norm(c - p.c))
        t = tj.get(j["child"])
        if t is not None and t["parent"] == j["parent"]:
            tc = np.array(t["c"])
            if t.get("hinge"):
                a = np.array(t["axis_child"])
                ours.append(np.linalg.norm(np.cross(c - tc, a)))
                theirs.append(np.linalg.norm(np.cross(p.c - tc, a)))
            else:
                ours.append(np.linalg.norm(c - tc))
                theirs.append(np.linalg.norm(p.c - tc))
    return len(res["joints"]), ball, hinge, d_plain, ours, theirs


def mm(x):
    return f"{1000 * x:6.2f}" if x == x else "     —"


def main() -> None:
    argparse.ArgumentParser(description=__doc__.splitlines()[0]).parse_args()
    cases = []
    for seed in (1, 2, 3):
        cases.append((f"exercise 37 s 120 Hz, 14-bit, seed {seed}", "human", "exercise", 37, 120, seed, {"quantise": 72}))
    cases += [
        ("exercise, 3× tracker noise", "human", "exercise", 37, 120, 3, {"quantise": 72, "noise_scale": 3.0}),
        ("exercise, true wrist/ankle hinges", bodies.with_hinges(bodies.human(seed=1)), "exercise", 37, 120, 1, {"quantise": 72}),
        ("walk 30 s 144 Hz", "human", "walk", 30, 144, 1, {}),
        ("kiosk 30 s 144 Hz", "human", "kiosk", 30, 144, 1, {}),
        ("idle (standing) 30 s, seed 1", "human", "idle", 30, 120, 1, {}),
        ("idle (standing) 30 s, seed 5", "human", "idle", 30, 120, 5, {}),
    ]
    print(f"{'take':<40} {'joints':>6} {'ball':>4} {'hinge':>5} {'max |−plain| mm':>15} "
          f"{'truth err mm: ours med/max':>27} {'plain med/max':>14}")
    for label, model, motion, secs, rate, seed, faults in cases:
        take, truth = simulate(model, motion, seconds=secs, rate_hz=rate, seed=seed, faults=faults)
        n, b, h, dp, ours, theirs = evaluate(take, truth, truth["parent"])
        dmax = max(dp) if dp else float("nan")
        o = (np.median(ours), max(ours)) if ours else (np.nan, np.nan)
        t = (np.median(theirs), max(theirs)) if theirs else (np.nan, np.nan)
        print(f"{label:<40} {n:>6} {b:>4} {h:>5} {mm(dmax):>15} {mm(o[0]):>13}/{mm(o[1]):<13} {mm(t[0])}/{mm(t[1])}")
    try:
        from real_captures import KNEE, UPPER_LIMB, cluster_take, segment_map
        import pytest  # noqa: F401  (real_captures skips through pytest when the data are absent)

        for name in (KNEE, UPPER_LIMB):
            take = cluster_take(name)
            for how, hier in (("anatomical tree", {c: p for c, p in segment_map(name)["anatomical_parent"].items()
                                                   if c in take.names and p in take.names}), ("searched tree", None)):
                try:
                    n, b, h, dp, _, _ = evaluate(take, None, hier)
                except Exception as exc:  # the upper-limb map leaves the box without a parent
                    print(f"{name + ', ' + how:<40} {exc}")
                    continue
                print(f"{name + ', ' + how:<40} {n:>6} {b:>4} {h:>5} {mm(max(dp) if dp else float('nan')):>15}")
    except BaseException as exc:  # pytest's Skipped is a BaseException
        print(f"real captures skipped: {exc}")


if __name__ == "__main__":
    main()
