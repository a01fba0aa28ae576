"""The figures of docs/outputs.md and docs/service.md ("Saved skeletons") that no test states: how long
`export-bvh` and `report` take on a 16-sensor take, the unit-scale factor over many seeds, and a saved
skeleton on the performer's next take (bones, placements, cost of a cold and a warm fit).

    python benchmarks/bench_outputs.py [--only bvh report scale skeleton] [--scale-seeds 12]

Prints figures; asserts nothing. Times are wall time of one process on one core (OPENBLAS_NUM_THREADS=1;
the load average is printed): the commands run in-process, so Python's start-up is not in them.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # one core's figures (set before numpy loads BLAS)

import argparse  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from dataclasses import replace  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from flockcal.cli import main  # noqa: E402
from flockcal.exports.skeleton import load_skeleton, write_skeleton  # noqa: E402
from flockcal.simulator.body import human  # noqa: E402
from flockcal.simulator.take import simulate  # noqa: E402
from flockcal.solver.accumulator import GramAccumulator  # noqa: E402
from flockcal.solver.calibration import calibrate  # noqa: E402
from flockcal.solver.known_skeleton import fit_saved, known_fit  # noqa: E402
from flockcal.solver.scale import rigid_pair_scale  # noqa: E402
from flockcal.takes import make_take, save_take  # noqa: E402


def _timed(fn, repeat: int = 1) -> float:
    best = np.inf
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best


def _acc(take) -> GramAccumulator:
    return GramAccumulator(take.n_sensors).add_poses(take.rotations, take.positions, take.valid)


def bench_bvh_and_report(folder: Path, only: set[str]) -> None:
    take, _ = simulate("human", "exercise", seconds=60, rate_hz=144, seed=1)
    path = folder / "take.npz"
    save_take(path, take)
    print(f"take: {take.n_frames} frames x {take.n_sensors} sensors")
    if "bvh" in only:
        out = folder / "take.bvh"
        sec = _timed(lambda: main(["export-bvh", str(path), "-o", str(out)]), repeat=2)
        print(f"export-bvh: {sec:.2f} s (best of 2, the fit included), {out.stat().st_size / 1e6:.1f} MB")
    if "report" in only:
        out = folder / "report.html"
        sec = _timed(lambda: main(["report", str(path), "-o", str(out)]), repeat=2)
        print(f"report: {sec:.2f} s (best of 2, the fit and slip scan included), {out.stat().st_size / 1e6:.1f} MB")


def bench_scale(seeds: int) -> None:
    unit, distance = 1.03, 0.565  # as tests/test_outputs_scale.py: ranges 3 % long, the paper's rigid pair
    errs, ratios = [], []
    for seed in range(1, seeds + 1):
        take, _ = simulate("pair", motion="walk", seconds=20, rate_hz=100, seed=seed, faults={"unit_scale": unit})
        est = rigid_pair_scale(take.positions[:, 0], take.positions[:, 1], distance, valid=take.valid.all(axis=1),
                               rotations_a=take.rotations[:, 0], rotations_b=take.rotations[:, 1])
        err = abs(est.factor * unit - 1)
        errs.append(err)
        ratios.append(abs(est.factor - 1 / unit) / est.factor_stderr)
        print(f"  seed {seed:2d}: factor error {100 * err:.3f} %, stated stderr {100 * est.factor_stderr * unit:.3f} %")
    print(f"scale, {seeds} seeds: median {100 * np.median(errs):.3f} %, worst {100 * max(errs):.3f} %; "
          f"error / stated stderr worst {max(ratios):.1f}")


def _head(take, k: int):
    return make_take(take.rotations[:k], take.positions[:k], list(take.names), take.rate_hz,
                     valid=take.valid[:k], times=take.times[:k])


def _bones(d: dict) -> dict:
    """Bone lengths keyed by their two joints, each joint by its two bodies (a joint is named by its child,
    which depends on where the fitted tree is rooted)."""
    key = {j["child"]: frozenset((j["child"], j["parent"])) for j in d["joints"]}
    return {frozenset((key[b["from_joint"]], key[b["to_joint"]])): b["length_m"] for b in d["bones"]}


def bench_skeleton(folder: Path) -> None:
    # As tests/test_outputs_skeleton.py, but a 45 s first take: every sensor put back ~2 cm and ~10° away.
    first = human(seed=0)
    rng = np.random.default_rng(5)
    second = replace(first, sensor_offset=first.sensor_offset + rng.normal(0, 0.02, first.sensor_offset.shape),
                     sensor_rotation=Rotation.from_rotvec(rng.normal(0, 0.2, (first.m, 3))).as_matrix()
                     @ first.sensor_rotation)
    take1, _ = simulate(first, "exercise", seconds=45, seed=1, birds=None, sta_mm=0)
    take2, truth2 = simulate(second, "walk", seconds=20, seed=2, birds=None, sta_mm=0)
    cal1 = calibrate(_acc(take1), names=list(take1.names))
    path = folder / "performer.json"
    write_skeleton(path, cal1, {"take": "first.npz", "frames": take1.n_frames, "rate_hz": take1.rate_hz})
    skeleton = load_skeleton(path)
    truth_bones = _bones(truth2)
    truth_c = {(j["child"], j["parent"]): np.array(j["c"]) for j in truth2["joints"] if not j["hinge"]}

    def bone_err(d):
        e = [abs(v - truth_bones[k]) * 1e3 for k, v in _bones(d).items() if k in truth_bones]
        return np.median(e), max(e), len(e)

    med, worst, n = bone_err(cal1.to_dict())
    print(f"saved bones ({n} matched to the truth): median {med:.1f} mm, max {worst:.1f} mm")
    parent = cal1.to_dict()["parent"]
    for seconds in (3.0, 20.0):
        k = int(seconds * take2.rate_hz)
        part = _head(take2, k)
        acc = _acc(part)
        saved = fit_saved(skeleton, acc, part.names).to_dict()
        free = calibrate(acc, hierarchy=parent, names=list(part.names)).to_dict()
        fm, fw, _ = bone_err(free)
        placed = [np.linalg.norm(np.array(j["c"]) - truth_c[(j["child"], j["parent"])]) * 1e3
                  for j in saved["joints"] if (j["child"], j["parent"]) in truth_c]
        sm, sw, _ = bone_err(saved)
        print(f"next take, first {seconds:g} s: saved skeleton's bones {sm:.1f} / {sw:.1f} mm (median / max), "
              f"free fit of the same tree {fm:.1f} / {fw:.1f} mm; ball joints placed {np.median(placed):.1f} mm "
              f"median from the new truth ({len(placed)})")
    acc = _acc(take2)
    cold = _timed(lambda: known_fit(skeleton, acc, take2.names), repeat=5)
    last = known_fit(skeleton, acc, take2.names)
    warm = _timed(lambda: known_fit(skeleton, acc, take2.names, previous=last), repeat=5)
    short = _head(take2, int(16 * take2.rate_hz))
    acc16 = _acc(short)
    free = _timed(lambda: calibrate(acc16, names=list(short.names)), repeat=5)
    print(f"known-skeleton fit, 16 sensors: cold (two starts) {cold * 1e3:.1f} ms, warm {warm * 1e3:.1f} ms; "
          f"free calibrate (16 s take, tree searched) {free * 1e3:.1f} ms (best of 5)")


def run() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", nargs="+", default=["bvh", "report", "scale", "skeleton"],
                    choices=["bvh", "report", "scale", "skeleton"])
    ap.add_argument("--scale-seeds", type=int, default=12)
    args = ap.parse_args()
    only = set(args.only)
    print(f"load average {os.getloadavg()[0]:.1f}")
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        if only & {"bvh", "report"}:
            bench_bvh_and_report(folder, only)
        if "scale" in only:
            bench_scale(args.scale_seeds)
        if "skeleton" in only:
            bench_skeleton(folder)


if __name__ == "__main__":
    run()
