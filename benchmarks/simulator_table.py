"""The simulator's accuracy table of docs/simulator.md ("Measured"): for each routine, the tracker-noise
position and orientation error against the exact take, the share of sensor-frames past the Flock's
36-inch range, and the weakest ball joint's coverage axis.

Run: python benchmarks/simulator_table.py [--seconds 45] [--rate 100] [--seed 1]
"""

from __future__ import annotations

import argparse

import numpy as np

from flockcal.simulator.take import simulate
from flockcal.solver.accumulator import GramAccumulator
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
    acc.update(noisy.rotations, noisy.positions, noisy.valid)
    names = list(noisy.names)
    joints = truth["joints"]
    pairs = np.array([[names.index(j["child"]), names.index(j["parent"])] for j in joints])
    ball = np.array([not j["hinge"] for j in joints])
    coverage = pair_fits(acc, pairs).coverage  # sorted ascending per joint
    return (float(np.sqrt(np.mean(dp**2))), float(np.degrees(np.sqrt(np.mean(angle**2)))), float(far),
            float(coverage[ball, 0].min()), float(coverage.max()))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=45.0)
    ap.add_argument("--rate", type=float, default=100.0)
    ap.add_argument("--seed", type=int, default=1)
    a = ap.parse_args()
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
