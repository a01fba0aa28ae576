"""High-frequency noise of joint residuals in each sensor's own frame, the noise the frame-rate step test
(docs/slippage.md, "Fourth round") weighs a step against: per-axis sd from first, second and third
differences (white noise gives the same from all three; a filter that correlates successive samples gives
less from the higher ones), on the real captures in ../shared/data (optical clusters as 6-DOF sensors,
anatomical joints, a whole-take fit) and on the simulator (kiosk and exercise, 12 mm soft tissue, 144 Hz).

    python benchmarks/bench_frame_noise.py            # real captures (needs ezc3d and ../shared/data)
    python benchmarks/bench_frame_noise.py --sim      # and the simulator
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from flockcal.solver.accumulator import GramAccumulator
from flockcal.solver.fits import pair_fits
from flockcal.solver.slippage.stats import sensor_frame_residuals

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # the real takes are built as the tests build them
from bench_slippage import frames, tree  # noqa: E402


def robust_sd(x: np.ndarray) -> np.ndarray:
    return 1.4826 * np.nanmedian(np.abs(x - np.nanmedian(x, axis=0)), axis=0)


def report(label: str, names, times, R, t, valid, J) -> None:
    acc = GramAccumulator(len(names))
    acc.add_poses(R, t, valid)
    fits = pair_fits(acc, J)
    u, _ = sensor_frame_residuals(R, t, J, fits.c, fits.l)
    pv = valid[:, J[:, 0]] & valid[:, J[:, 1]]
    u = np.where(pv[..., None], u, np.nan)
    rate = 1.0 / np.median(np.diff(times))
    print(f"{label}: {len(times)} frames at {rate:.0f} Hz; per-axis sd (mm, median of the three axes) from "
          "1st / 2nd / 3rd differences, and the residual's own rms")
    for k, (ci, pi) in enumerate(J):
        sds = [np.median(robust_sd(np.diff(u[:, k], n, axis=0))) / np.sqrt(s) for n, s in ((1, 2), (2, 6), (3, 20))]
        rms = np.sqrt(np.nanmean((u[:, k] - np.nanmean(u[:, k], axis=0)) ** 2))
        print(f"  {names[ci]:>12}-{names[pi]:<12} {1e3 * sds[0]:6.2f} {1e3 * sds[1]:6.2f} {1e3 * sds[2]:6.2f}   rms {1e3 * rms:5.1f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sim", action="store_true", help="the simulator too")
    args = ap.parse_args()
    from real_captures import KNEE, UPPER_LIMB, cluster_take, segment_map

    for cap in (KNEE, UPPER_LIMB):
        take = cluster_take(cap)
        parent = segment_map(cap)["anatomical_parent"]
        J = np.array([[take.index(c), take.index(p)] for c, p in parent.items() if c in take.names and p in take.names])
        report(cap, take.names, take.times, take.rotations, take.positions, take.valid, J)
    if args.sim:
        from flockcal.simulator.performer import Performer

        for routine in ("kiosk", "exercise"):
            perf = Performer("human", routine=routine, seed=1, noise="tracker", rate_hz=144, sta_mm=12)
            ts, R, t, v = frames(perf, 144, 0.0, 30.0)
            report(f"simulator, {routine}", perf.names, ts, R, t, v, tree(perf.model))


if __name__ == "__main__":
    main()
