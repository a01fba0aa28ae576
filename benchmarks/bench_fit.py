"""Fit benchmark (design.md §6): frames/s of the reference SVD, the Gram batch and incremental paths, and refit time.

Run: python benchmarks/bench_fit.py [--frames N] [--sensors M]. Prints figures and ratios; asserts nothing.
Single-core figures: set OPENBLAS_NUM_THREADS=1 (done below unless already set).
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from synthetic import articulated  # noqa: E402

from flockcal.solver.accumulator import GramAccumulator  # noqa: E402
from flockcal.solver.calibration import calibrate  # noqa: E402
from flockcal.solver.fits import all_pairs, pair_fits  # noqa: E402
from reference import reference_pair_fit  # noqa: E402
from flockcal.solver.topology import spanning_tree  # noqa: E402


def best_of(fn, repeat=3):
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return min(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--frames", type=int, default=200_000)
    ap.add_argument("--sensors", type=int, default=16)
    args = ap.parse_args()
    m, n = args.sensors, args.frames
    d = articulated(m=m, n=min(n, 20_000), seed=1, position_noise=5e-4, rotation_noise=0.002)
    reps = -(-n // len(d.rotations))
    R = np.concatenate([d.rotations] * reps)[:n]
    t = np.concatenate([d.positions] * reps)[:n]
    pairs = all_pairs(m)
    print(f"{m} sensors ({len(pairs)} pairs), {n} frames, OPENBLAS_NUM_THREADS={os.environ['OPENBLAS_NUM_THREADS']}")

    # (a) the paper's per-pair stacked SVD, over all pairs (on a slice: it is slow)
    nr = min(n, 5_000)
    sec = best_of(lambda: [reference_pair_fit(R[:nr, i], t[:nr, i], R[:nr, j], t[:nr, j]) for i, j in pairs], 1)
    ref_fps = nr / sec
    print(f"(a) reference SVD, all pairs:        {ref_fps:14,.0f} frames/s")

    # (b) Gram batch path: accumulate + all-pair fits + MST
    def batch():
        acc = GramAccumulator(m).add_poses(R, t)
        spanning_tree(pair_fits(acc), m)

    batch_fps = n / best_of(batch)
    acc_only = n / best_of(lambda: GramAccumulator(m).add_poses(R, t).gram)
    print(f"(b) Gram batch (accumulate + fit):   {batch_fps:14,.0f} frames/s   (accumulate only {acc_only:,.0f})")

    # (c) incremental path: 1-frame and 64-frame updates
    n1 = min(n, 50_000)

    def one_by_one():
        acc = GramAccumulator(m)
        for k in range(n1):
            acc.add_poses(R[k], t[k])
        acc.gram

    def by_64():
        acc = GramAccumulator(m)
        for s in range(0, n, 64):
            acc.add_poses(R[s:s + 64], t[s:s + 64])
        acc.gram

    inc1 = n1 / best_of(one_by_one, 2)
    inc64 = n / best_of(by_64, 2)
    print(f"(c) incremental, 1-frame updates:    {inc1:14,.0f} frames/s")
    print(f"    incremental, 64-frame updates:   {inc64:14,.0f} frames/s")

    # refit all pairs + MST from the Gram, and the whole calibrate() the live server calls
    acc = GramAccumulator(m).add_poses(R, t)
    k = 50
    refit = best_of(lambda: [spanning_tree(pair_fits(acc), m) for _ in range(k)]) / k
    cal = best_of(lambda: [calibrate(acc) for _ in range(k)]) / k
    fit_only = best_of(lambda: [pair_fits(acc) for _ in range(k)]) / k
    print(f"refit all pairs + MST:               {1e3 * refit:10.2f} ms   (pair fits alone {1e3 * fit_only:.2f} ms)")
    print(f"calibrate() (fits + MST + bones):    {1e3 * cal:10.2f} ms   = {1 / cal:,.0f} refreshes/s")
    print()
    print("ratios")
    print(f"  Gram batch / reference SVD:        {batch_fps / ref_fps:10.0f}x")
    print(f"  Gram batch / 1,000,000 target:     {batch_fps / 1e6:10.2f}x")
    print(f"  64-frame / 1-frame incremental:    {inc64 / inc1:10.1f}x")
    print(f"  10 ms / refit + MST:               {0.010 / refit:10.1f}x")
    print(f"  16 birds x 144 Hz / 1-frame path:  {inc1 / (144):10.0f}x real time")


if __name__ == "__main__":
    main()
