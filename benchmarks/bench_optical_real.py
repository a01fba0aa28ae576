"""`flockcal fit-markers` on real captures, timed as a user runs it: a fresh process, start-up included.
Targets (issue 31; issue 17 had 5 s for knee17): ≤ 2 s of wall time for 73 markers × 17 s at 100 Hz, ≤ 1 s
for the pyomeca file. The simulated 46-marker walk (≤ 3 s) is timed by bench_optical_sim.py --fresh.

Inputs, from ../shared/data (or $FLOCKCAL_SHARED_DATA):
- `pyomeca`: pyomeca_markers_analogs.c3d as it is (51 markers, 5.8 s, ~1 % gaps);
- `knee`: biobuddy_right_knee.c3d as it is (73 markers, 9.2 s);
- `knee17`: the knee trial followed by itself played backwards, cut to 17 s (73 markers × 1700 frames,
  the size of the hip trial; backwards so the motion is continuous where the two meet), as a marker .npz.

Each input runs `--repeat` times; the table gives the fastest wall time, its CPU time (user + system of
the child) and wall/target. On a shared machine wall time follows the load: CPU time is the steadier
figure, and the script prints the load average beside it.

    python benchmarks/bench_optical_real.py                 # 3 runs each
    python benchmarks/bench_optical_real.py --repeat 5 --only knee17
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

SHARED = Path(os.environ.get("FLOCKCAL_SHARED_DATA", Path(__file__).resolve().parents[1].parent / "shared" / "data"))
TARGETS_S = {"pyomeca": 1.0, "knee": None, "knee17": 2.0}


def knee17(out: Path) -> Path:
    """The knee trial, then itself backwards, cut to 1700 frames at 100 Hz, as a marker .npz."""
    from flockcal.markers import load_c3d, make_marker_take, save_markers

    mt = load_c3d(SHARED / "biobuddy_right_knee.c3d")
    M = np.concatenate([mt.markers, mt.markers[::-1][1:]], axis=0)[:1700]
    path = out / "knee17.npz"
    save_markers(path, make_marker_take(M, mt.marker_names, mt.rate_hz, source="knee17"))
    return path


def run_once(path: Path) -> tuple[float, float]:
    """(wall s, child CPU s) of one `flockcal fit-markers PATH --json` in a fresh interpreter."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "flockcal", "fit-markers", str(path), "--json"],
                          capture_output=True, text=True, check=False)  # fmt: skip
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        sys.exit(f"fit-markers {path} failed: {proc.stderr.strip()}")
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--only", choices=sorted(TARGETS_S), action="append")
    args = ap.parse_args()
    if not (SHARED / "pyomeca_markers_analogs.c3d").exists():
        sys.exit(f"the real captures are not in {SHARED}: clone beside ../shared or set FLOCKCAL_SHARED_DATA")
    with tempfile.TemporaryDirectory() as tmp:
        inputs = {
            "pyomeca": SHARED / "pyomeca_markers_analogs.c3d",
            "knee": SHARED / "biobuddy_right_knee.c3d",
            "knee17": knee17(Path(tmp)),
        }
        print(f"load average before: {' '.join(f'{x:.1f}' for x in os.getloadavg())}  (cores: {os.cpu_count()})")
        print(f"{'input':<8} {'wall s':>7} {'cpu s':>6} {'target s':>8} {'wall/target':>11}")
        for name, path in inputs.items():
            if args.only and name not in args.only:
                continue
            runs = [run_once(path) for _ in range(args.repeat)]
            wall, cpu = min(runs)
            target = TARGETS_S[name]
            ratio = f"{wall / target:.2f}" if target else "-"
            print(f"{name:<8} {wall:7.2f} {cpu:6.2f} {target or '-':>8} {ratio:>11}")
        print(f"load average after: {' '.join(f'{x:.1f}' for x in os.getloadavg())}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
