"""Wall time of `flockcal fit TAKE` with its slip scan on a 30 s, 16-sensor, 144 Hz take (design.md §6:
≤ 1 s, start-up included), against the same fit without the scan, the import time, and what the live
slip monitor costs the service at 16 birds × 144 Hz (its CPU budget is 25 % of a core in all); with
--old-rev, the same slip scan and live monitor of an earlier commit, run side by side in this run.

    python benchmarks/bench_fit_slips.py [--runs 5] [--motion exercise] [--sta-mm 12] [--old-rev 38b60ff]

Prints figures and ratios; asserts nothing. Each `flockcal fit` is a fresh process, as a user runs it.
"""

from __future__ import annotations

import os

# One BLAS thread, as `flockcal fit` uses (flockcal.threads.single_threaded_blas), for the in-process
# figures too; set OPENBLAS_NUM_THREADS to see the service's default instead.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

RATE = 144.0
SECONDS = 30.0
TARGET_S = 1.0


def run(cmd: list[str], runs: int) -> tuple[float, float, float]:
    """(best, median wall seconds, median CPU seconds of the child) over `runs` fresh processes."""
    walls, cpus = [], []
    for _ in range(runs):
        before = os.times()
        t0 = time.perf_counter()
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
        walls.append(time.perf_counter() - t0)
        after = os.times()
        cpus.append((after.children_user - before.children_user) + (after.children_system - before.children_system))
    return min(walls), float(np.median(walls)), float(np.median(cpus))


def import_seconds(module: str, runs: int) -> float:
    best = np.inf
    for _ in range(runs):
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-c", f"import {module}"], check=True)
        best = min(best, time.perf_counter() - t0)
    return best


# The slip modules before solver/slippage/ became a package (issue 33), and their names inside it.
MODULES = {"slippage": "monitor", "slippage_stats": "stats", "slippage_attribution": "attribution",
           "slippage_local": "baseline", "slippage_revisit": "revisit", "slippage_buffer": "buffer",
           "slippage_pending": "pending", "slippage_framestep": "framestep", "slippage_events": "events",
           "slippage_settings": "settings", "slippage_steptest": "steptest", "slippage_confirming": "confirming",
           "slippage_framescan": "framescan"}


def old_monitor(rev: str, folder: Path):
    """The slippage modules of commit `rev` (git show; flat or in the package), importable beside today's
    under other names."""
    root = Path(__file__).resolve().parents[1]

    def show(path: str) -> str | None:
        got = subprocess.run(["git", "-C", str(root), "show", f"{rev}:{path}"], capture_output=True, text=True)
        return None if got.returncode else got.stdout  # that commit did not have this module

    for flat, inner in MODULES.items():
        text = show(f"solver/slippage/{inner}.py") or show(f"solver/{flat}.py")
        if text is None:
            continue
        for other_flat, other in MODULES.items():
            text = text.replace(f"from flockcal.solver.slippage.{other} import", f"from old_slippage_{other} import")
            text = text.replace(f"from flockcal.solver.{other_flat} import", f"from old_slippage_{other} import")
        (folder / f"old_slippage_{inner}.py").write_text(text)
    sys.path.insert(0, str(folder))
    import old_slippage_monitor

    return old_slippage_monitor


def live_monitor_share(sta_mm: float, seconds: float = 60.0, module=None) -> tuple[float, int]:
    """CPU seconds per second of data of a SlipMonitor fed as the service feeds it (every 0.1 s, with
    estimates that move a little each time), 16 birds at 144 Hz; and the (false) alarms it raised."""
    from flockcal.simulator.performer import Performer
    from flockcal.solver.accumulator import GramAccumulator
    from flockcal.solver.fits import pair_fits
    from flockcal.solver.slippage import SlipMonitor

    if module is not None:
        SlipMonitor = module.SlipMonitor  # noqa: N806
    perf = Performer("human", routine="exercise", seed=2, rate_hz=RATE, seconds=seconds, period=seconds, sta_mm=sta_mm)
    J = np.array([[i, int(p)] for i, p in enumerate(perf.model.parent) if p >= 0])
    times = np.arange(int(seconds * RATE)) / RATE
    R, t, v = perf.poses(times)
    acc = GramAccumulator(perf.n_sensors)
    acc.add_poses(R, t, v)
    fits = pair_fits(acc, J)
    mon = SlipMonitor(J, perf.n_sensors, RATE, perf.names)
    add_frames = getattr(mon, "add_frames", None) or mon.update  # `update` before issue 33's rename
    step = int(round(0.1 * RATE))
    rng = np.random.default_rng(0)
    cpu = 0.0
    for a in range(0, len(times), step):
        sl = slice(a, a + step)
        jitter = rng.normal(scale=1e-4, size=fits.c.shape)  # a running fit moves between refits
        c0 = time.process_time()
        add_frames(times[sl], R[sl], t[sl], v[sl], fits.c + jitter, fits.l - jitter)
        cpu += time.process_time() - c0
    return cpu / seconds, len(mon.events)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--motion", default="exercise")
    ap.add_argument("--sta-mm", type=float, default=12.0)
    ap.add_argument("--old-rev", help="also run the slip scan and live monitor of this git commit (e.g. 38b60ff)")
    args = ap.parse_args()
    flockcal = [sys.executable, "-m", "flockcal"]
    with tempfile.TemporaryDirectory() as tmp:
        take = Path(tmp) / "take.npz"
        subprocess.run(flockcal + ["simulate", "--motion", args.motion, "--seconds", str(SECONDS), "--rate", str(RATE),
                                   "--birds", "16", "--seed", "1", "--sta-mm", str(args.sta_mm), "-o", str(take)],
                       check=True, stdout=subprocess.DEVNULL)
        full = run(flockcal + ["fit", str(take), "--json"], args.runs)
        bare = run(flockcal + ["fit", str(take), "--json", "--no-slips"], args.runs)
        scans = {}
        if args.old_rev:
            from flockcal.commands.fit import accumulate
            from flockcal.solver import slippage
            from flockcal.solver.calibration import calibrate
            from flockcal.takes import load_take

            old = old_monitor(args.old_rev, Path(tmp))
            data = load_take(take)
            cal = calibrate(accumulate(data, progress=False), names=data.names)
            for label, module in (("today", slippage), (args.old_rev, old)):
                best, events = np.inf, []
                for _ in range(args.runs):
                    c0 = time.process_time()
                    events = module.detect_slips(data, cal)
                    best = min(best, time.process_time() - c0)
                scans[label] = (best, len(events), module)
    start = import_seconds("flockcal.cli", args.runs)
    solver = import_seconds("flockcal.solver.calibration", args.runs) - start
    slips = import_seconds("flockcal.solver.slippage", args.runs) - start
    print(f"flockcal fit, {SECONDS:g} s x 16 sensors at {RATE:g} Hz ({args.motion}, STA {args.sta_mm:g} mm), {args.runs} runs, fresh processes")
    print(f"  with the slip scan:     best {full[0]:.2f} s, median {full[1]:.2f} s wall ({full[2]:.2f} s CPU)")
    print(f"  without (--no-slips):   best {bare[0]:.2f} s, median {bare[1]:.2f} s wall ({bare[2]:.2f} s CPU)")
    print(f"  the slip scan itself:   {full[1] - bare[1]:.2f} s wall (median difference)")
    print(f"  start-up: interpreter + flockcal.cli {start:.2f} s; solver imports +{solver:.2f} s; slippage imports +{slips:.2f} s")
    print(f"  ratio to the {TARGET_S:g} s target: {full[1] / TARGET_S:.2f} (median), {full[0] / TARGET_S:.2f} (best)")
    for label, (cpu, events, _) in scans.items():
        print(f"  detect_slips in-process, {label}: {cpu:.2f} s CPU, {events} slip events (nothing slipped)")
    if len(scans) == 2:
        print(f"  ratio {args.old_rev} / today: {scans[args.old_rev][0] / scans['today'][0]:.1f}x")
    share, alarms = live_monitor_share(args.sta_mm)
    print(f"live SlipMonitor, 16 birds at {RATE:g} Hz in 0.1 s batches (exercise, STA {args.sta_mm:g} mm, 60 s): "
          f"{100 * share:.1f} % of one core, {alarms} alarms")
    if args.old_rev:
        share_old, alarms_old = live_monitor_share(args.sta_mm, module=scans[args.old_rev][2])
        print(f"  the same with {args.old_rev}: {100 * share_old:.1f} % of one core, {alarms_old} alarms "
              f"(ratio {share_old / share:.1f}x)")
    print(f"  (OPENBLAS_NUM_THREADS={os.environ['OPENBLAS_NUM_THREADS']} here; flockcal fit uses one BLAS thread)")


if __name__ == "__main__":
    main()
