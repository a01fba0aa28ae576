"""Size and write time of the glTF rig (issue 34, item 5: a 30 s, 16-sensor take's .glb under 2 MB,
written in under 1 s), beside the BVH and the TRC of the same take. Prints figures, asserts nothing.

The take is the simulated human (16 birds, exercise routine, tracker noise), fitted once; the writes are
timed from the fit to the bytes (reconstruction, rotations, figure, container), best and median of 5. The
rig is the VRM 1.0 humanoid (the default: the humanoid found on a sample of the take, the tree hung from
the hips); "plain" is the same take's rig with the first frame as its rest (`rest="first"`), and
vrm/plain the ratio of their medians: what the VRM costs.

    python benchmarks/bench_gltf.py [--seconds 30] [--rates 100 144]
"""

from __future__ import annotations

import argparse
import statistics
import time

from flockcal.exports.bvh import bvh_bytes
from flockcal.exports.gltf import gltf_bytes
from flockcal.exports.trc import trc_text
from flockcal.simulator.take import simulate
from flockcal.solver.accumulator import GramAccumulator
from flockcal.solver.calibration import calibrate


def timed(fn, repeats: int = 5) -> tuple[float, float, bytes]:
    times, out = [], b""
    for _ in range(repeats):
        start = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - start)
    return min(times), statistics.median(times), out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=30.0)
    ap.add_argument("--rates", type=float, nargs="+", default=[100.0, 144.0])
    args = ap.parse_args()
    print(f"{'rate Hz':>7} {'frames':>7} {'glb MB':>7} {'best s':>7} {'median s':>8} {'gltf MB':>8} "
          f"{'plain s':>7} {'vrm/plain':>9} {'bvh MB':>7} {'bvh s':>6} {'trc MB':>7} {'trc s':>6}")
    for rate in args.rates:
        take, _ = simulate("human", "exercise", seconds=args.seconds, rate_hz=rate, seed=1, birds=16)
        acc = GramAccumulator(take.n_sensors)
        acc.add_poses(take.rotations, take.positions, take.valid)
        cal = calibrate(acc, names=list(take.names))
        best, median, glb = timed(lambda: gltf_bytes(cal, take))
        _, _, text = timed(lambda: gltf_bytes(cal, take, binary=False), 1)
        _, plain_median, _ = timed(lambda: gltf_bytes(cal, take, rest="first"))
        _, bvh_median, bvh = timed(lambda: bvh_bytes(cal, take))
        _, trc_median, trc = timed(lambda: trc_text(cal, take))
        print(f"{rate:7.0f} {take.n_frames:7d} {len(glb) / 1e6:7.2f} {best:7.3f} {median:8.3f} {len(text) / 1e6:8.2f} "
              f"{plain_median:7.3f} {median / plain_median:9.2f} {len(bvh) / 1e6:7.2f} {bvh_median:6.3f} "
              f"{len(trc) / 1e6:7.2f} {trc_median:6.3f}")


if __name__ == "__main__":
    main()
