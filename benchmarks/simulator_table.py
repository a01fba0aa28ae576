"""The simulator's accuracy table of docs/simulator.md ("Measured"): for each routine, the tracker-noise
position and orientation error against the exact take, the share of sensor-frames past the Flock's
36-inch range, and the weakest ball joint's coverage axis.

Run: python benchmarks/simulator_table.py [--seconds 45] [--rate 100] [--seed 1]
     python benchmarks/simulator_table.py --accuracy 1 2 3 4 5   # the fit against the truth instead
With --accuracy: "exercise" with tracker noise on rigid sensors, per seed: the worst and median distance of
a fitted joint centre from the true one (a hinge's: from its true axis line), the worst bone, and whether
the tree is the true one.
"""

from __future__ import annotations

import argparse

import numpy as np

from flockcal.simulator.take import simulate
from flockcal.solver.accumulator import GramAccumulator
from flockcal.solver.calibration import calibrate
from flockcal.solver.fits import pair_fits

INCH = 0.0254


def row(motion: str, seconds: float, rate: float, seed: int) -> tuple[float, float, float, float]:
    noisy, truth = simulate(motion=motion, seconds=seconds, rate_hz=rate, seed=seed, noise="tracker")
    exact, _ = simulate(motion=motion, seconds=seconds, rate_hz=rate, seed=seed, noise=None)
    ok = noisy.valid & exact.valid
    dp = np.linalg.norm(noisy.positions - exact.positions, axis=-1)[ok]
    rel = np.swapaxes(exact.rotations, -1, -2) @ noisy.rotations
    angle = np.arccos(np.clip((np.trace(rel, axis1=-2, axis2=-1) - 1) / 2, -1, 1))[ok]
    # The position words saturate per axis at the 36-inch full scale.
    far = (np.abs(exact.positions).max(axis=-1) > 36 * INCH).mean()
    acc = GramAccumulator(noisy.n_sensors)
    acc.add_poses(noisy.rotations, noisy.positions, noisy.valid)
    names = list(noisy.names)
    joints = truth["joints"]
    pairs = np.array([[names.index(j["child"]), names.index(j["parent"])] for j in joints])
    ball = np.array([not j["hinge"] for j in joints])
    coverage = pair_fits(acc, pairs).coverage  # sorted ascending per joint
    return (float(np.sqrt(np.mean(dp**2))), float(np.degrees(np.sqrt(np.mean(angle**2)))), float(far),
            float(coverage[ball, 0].min()), float(coverage.max()))


def accuracy(seconds: float, rate: float, seed: int) -> tuple[float, float, float, bool]:
    take, truth = simulate(motion="exercise", seconds=seconds, rate_hz=rate, seed=seed, noise="tracker", sta_mm=0)
    acc = GramAccumulator(take.n_sensors).add_poses(take.rotations, take.positions, take.valid)
    fit = calibrate(acc, names=list(take.names)).to_dict()
    true = {}
    for j in truth["joints"]:  # a joint's centre and axis in each of its two sensors' frames
        true[(j["child"], j["parent"])] = (np.array(j["c"]), j["hinge"] and np.array(j["axis_child"]))
        true[(j["parent"], j["child"])] = (np.array(j["l"]), j["hinge"] and np.array(j["axis_parent"]))
    errs = []
    for j in fit["joints"]:
        c, axis = true[(j["child"], j["parent"])]
        d = np.array(j["c"]) - c
        if axis is not False:
            d = d - axis * (d @ axis)
        errs.append(float(np.linalg.norm(d)))
    # Bones are named by their joints, each joint by its child: compare them by the joints' two bodies.
    def bones(doc):
        key = {j["child"]: frozenset((j["child"], j["parent"])) for j in doc["joints"]}
        return {frozenset((key[b["from_joint"]], key[b["to_joint"]])): b["length_m"] for b in doc["bones"]}
    tb, fb = bones(truth), bones(fit)
    bone = max(abs(fb[k] - tb[k]) for k in fb if k in tb)
    tree = {frozenset(p) for p in truth["parent"].items()} == {frozenset(p) for p in fit["parent"].items()}
    return max(errs), float(np.median(errs)), bone, tree


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=45.0)
    ap.add_argument("--rate", type=float, default=100.0)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--accuracy", type=int, nargs="+", metavar="SEED", help="the fit against the truth, these seeds")
    a = ap.parse_args()
    if a.accuracy:
        print(f"exercise, {a.seconds:g} s at {a.rate:g} Hz, tracker noise, rigid sensors (sta_mm=0)")
        for seed in a.accuracy:
            worst, median, bone, tree = accuracy(a.seconds, a.rate, seed)
            print(f"seed {seed}: joint centres worst {worst * 1e3:.2f} mm, median {median * 1e3:.2f} mm; "
                  f"worst bone {bone * 1e3:.2f} mm; tree {'right' if tree else 'WRONG'}")
        return
    print(f"{a.seconds:g} s at {a.rate:g} Hz, 16 sensors, seed {a.seed} (soft tissue at its default)")
    print("| routine | position error (3-D rms) | orientation error (rms) | sensor-frames past 36 in | coverage (weakest ball joint axis) |")
    print("|---|---|---|---|---|")
    for motion in ("exercise", "walk", "kiosk", "idle"):
        pos, ang, far, cov, top = row(motion, a.seconds, a.rate, a.seed)
        # Standing still turns no joint: say how small the largest axis of any joint is.
        shown = f"< {top:.4f} (every axis of every joint)" if motion == "idle" else f"{cov:.4f}"
        print(f"| {motion} | {pos * 1000:.1f} mm | {ang:.2f}° | {100 * far:.1f} % | {shown} |")


if __name__ == "__main__":
    main()
