"""Slippage monitor figures for the README: detection rate, attribution and delay of 2 cm slips of
every sensor over many seeds, and false alarms per hour of motion where nothing slips — with and
without soft-tissue artefact (STA: the simulator's skin moving with the joint angles).

    python benchmarks/bench_slippage.py                          # 20 seeds × 16 sensors, then a 1-hour soak
    python benchmarks/bench_slippage.py --seeds 5 --hours 0.1
    python benchmarks/bench_slippage.py --sta-mm 12 --seeds 10 --hours 1 --routine exercise
    python benchmarks/bench_slippage.py --sta-suite              # the STA runs: detection, soaks, 120 kiosk guests
    python benchmarks/bench_slippage.py --fresh 120 --routine kiosk --sta-mm 12   # 120 guests x 30 s
    python benchmarks/bench_slippage.py --phases head --routine exercise --rate 144 --seed 2   # one sensor, 40 moments
    python benchmarks/bench_slippage.py --tree-seeds 1 2 4       # the searched tree after a slip (docs/slippage.md)

Everything runs through the live loop (segmented accumulator → joint fits → SlipMonitor) in 1/30 s
micro-batches, as the server feeds it. `--sta-mm 0` (the default outside the suite) is the plain simulator.
"""

from __future__ import annotations

import argparse
import copy
import sys
import time
from pathlib import Path

import numpy as np

from flockcal.simulator.performer import Performer
from flockcal.solver.slippage.watch import SlipWatch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # the scoring rule is the tests'
from slip_scoring import attributes_slip_to  # noqa: E402


def tree(model) -> np.ndarray:
    return np.array([[i, int(p)] for i, p in enumerate(model.parent) if p >= 0])


def frames(perf: Performer, rate: float, t0: float, t1: float):
    times = np.arange(int(round(t0 * rate)), int(round(t1 * rate))) / rate
    R, t, v = perf.poses(times)
    return times, R, t, v


def detection(seeds: int, rate: float, distance: float, follow_s: float, routine: str = "walk",
              sta_mm: float = 0.0) -> None:
    delays, onset_err, strict, ok, missed, wrong, early = [], [], 0, 0, [], [], 0
    trials = 0
    start = time.perf_counter()
    for seed in range(seeds):
        rng = np.random.default_rng(seed)
        slip_at = float(np.round(rng.uniform(8.0, 20.0), 2))
        perf = Performer("human", routine=routine, seed=100 + seed, noise="tracker", rate_hz=rate, seconds=60,
                         sta_mm=sta_mm)
        base = SlipWatch(tree(perf.model), perf.n_sensors, rate, perf.names)
        base.feed(*frames(perf, rate, 0.0, slip_at))
        early += len(base.events)
        for name in perf.names:
            trials += 1
            replay = copy.deepcopy(base)
            perf.clear_faults()
            perf.inject_slip(name, distance, at_time=slip_at)
            found = replay.feed(*frames(perf, rate, slip_at, slip_at + follow_s))
            if not found:
                missed.append((seed, name))
                continue
            ev = found[0]
            delays.append(ev.detected_s - slip_at)
            onset_err.append(ev.time_s - slip_at)
            strict += ev.sensor == name
            if attributes_slip_to(ev, name, perf.model.names, perf.model.parent) and ev.detected_s - slip_at <= 0.5:
                ok += 1
            else:
                wrong.append((seed, name, ev.sensor, ev.candidates, round(ev.detected_s - slip_at, 3)))
    took = time.perf_counter() - start
    d = np.array(delays)
    skin = f"STA {sta_mm:g} mm" if sta_mm else "no STA"
    print(f"detection: {trials} trials ({seeds} seeds x 16 sensors), {distance * 100:.0f} cm slips during {routine} "
          f"at tracker noise, {skin}, {rate:.0f} Hz")
    print(f"  found and attributed within 0.5 s: {ok}/{trials} = {100 * ok / trials:.1f} %  "
          f"(exact sensor named first: {strict}/{trials}; missed within {follow_s} s: {len(missed)})")
    if len(d):
        print(f"  detection delay s: median {np.median(d):.3f}, p95 {np.percentile(d, 95):.3f}, max {d.max():.3f}")
        print(f"  onset time error s: median {np.median(np.abs(onset_err)):.3f}, max {np.max(np.abs(onset_err)):.3f}")
    print(f"  false alarms during the warm-up {routine}s: {early}")
    for w in wrong[:10]:
        print("  wrong/late:", w)
    for m in missed[:10]:
        print("  missed:", m)
    print(f"  ({took:.1f} s)", flush=True)


def phases(sensor: str, seed: int, rate: float, routine: str, sta_mm: float, start_s: float, stop_s: float,
           count: int, distance: float, follow_s: float = 1.0, monitor: dict | None = None) -> None:
    """One sensor slipped at `count` moments from start_s to stop_s of one performance (the service's
    exercise routine by default): which moments of the routine the monitor finds it late or not at all."""
    perf = Performer("human", routine=routine, seed=seed, noise="tracker", rate_hz=rate, sta_mm=sta_mm)
    base = SlipWatch(tree(perf.model), perf.n_sensors, rate, perf.names, **(monitor or {}))
    fed, late, delays = 0.0, [], []
    for at in np.round(np.linspace(start_s, stop_s, count), 3):
        perf.clear_faults()
        base.feed(*frames(perf, rate, fed, at))
        fed = at
        replay = copy.deepcopy(base)
        perf.inject_slip(sensor, distance, at_time=float(at))
        found = [e for e in replay.feed(*frames(perf, rate, at, at + follow_s))
                 if attributes_slip_to(e, sensor, perf.model.names, perf.model.parent)]
        delay = found[0].detected_s - at if found else float("inf")
        delays.append(delay)
        if delay > 0.5:
            late.append((float(at), round(float(delay), 2) if found else "missed"))
    d = np.array(delays)
    print(f"phases: {sensor} slipped {distance * 100:.0f} cm at {count} moments of {start_s:g}-{stop_s:g} s, {routine}, "
          f"seed {seed}, STA {sta_mm:g} mm, {rate:.0f} Hz; watched {follow_s:g} s after each"
          + (f"; monitor {monitor}" if monitor else ""))
    print(f"  found within {follow_s:g} s: {int(np.isfinite(d).sum())}/{count}; median delay "
          f"{np.median(d[np.isfinite(d)]) if np.isfinite(d).any() else float('nan'):.2f} s; late (> 0.5 s) or missed: {late}")


def tree_after_slips(seeds: list[int], rate: float = 100.0, slip_s: float = 15.0, after_s: float = 25.0) -> None:
    """docs/slippage.md "After a slip, the tree": each of the 16 sensors slipped 2 cm at `slip_s` in turn
    (exercise, tracker noise), a segment opened 0.5 s later as the live monitor would, the tree searched every
    second for `after_s` s: wrong trees of the segmented search (`SegmentedAccumulator.calibration`) against
    the whole-take one, the body's own parent list the oracle (as tests/test_segment_tree.py)."""
    from flockcal.solver.calibration import calibrate
    from flockcal.solver.segments import SegmentedAccumulator

    def edges(parent_map: dict) -> set:
        return {frozenset((c, p)) for c, p in parent_map.items() if p is not None}

    total = wrong = whole_wrong = 0
    step = int(rate // 2)
    for seed in seeds:
        for sensor in Performer("human", seed=seed).names:
            perf = Performer("human", routine="exercise", seed=seed, noise="tracker", rate_hz=rate, seconds=60)
            perf.inject_slip(sensor, 0.02, at_time=slip_s)
            times = np.arange(int((slip_s + after_s) * rate)) / rate
            R, t, v = perf.poses(times)
            names = list(perf.names)
            truth = edges({n: (names[p] if p >= 0 else None) for n, p in zip(names, perf.model.parent)})
            acc = SegmentedAccumulator(len(names))
            w = ww = 0
            for a in range(0, len(times), step):
                acc.ingest(times[a:a + step], R[a:a + step], t[a:a + step], v[a:a + step])
                if times[a] >= slip_s + 0.5 and not acc.segments:
                    acc.start_segment(names.index(sensor), slip_s)
                if times[a] >= slip_s + 1.0 and a % int(rate) == 0:
                    total += 1
                    w += edges(acc.calibration(names=names).parent_map()) != truth
                    ww += edges(calibrate(acc.whole, names=names).parent_map()) != truth
            wrong, whole_wrong = wrong + w, whole_wrong + ww
            print(f"  seed {seed} {sensor:12s}: wrong searches {w:2d} (whole take {ww:2d})", flush=True)
    print(f"tree after a slip, seeds {seeds}, 16 sensors, exercise at {rate:g} Hz: wrong trees in {wrong} of {total} "
          f"searches, against {whole_wrong} for the whole-take search")


def soak(hours: float, rate: float, routine: str = "walk", seed: int = 11, chunk_s: float = 60.0,
         sta_mm: float = 0.0, monitor: dict | None = None) -> None:
    seconds = hours * 3600.0
    # The kiosk routine is a half-minute loop by nature; the others are planned over the whole soak.
    period = None if routine == "kiosk" else max(seconds, 60.0)
    perf = Performer("human", routine=routine, seed=seed, noise="tracker", rate_hz=rate, seconds=seconds,
                     period=period, sta_mm=sta_mm)
    replay = SlipWatch(tree(perf.model), perf.n_sensors, rate, perf.names, **(monitor or {}))
    start = time.perf_counter()
    t0 = 0.0
    while t0 < seconds:
        t1 = min(seconds, t0 + chunk_s)
        replay.feed(*frames(perf, rate, t0, t1))
        t0 = t1
    took = time.perf_counter() - start
    n = len(replay.events)
    skin = f"STA {sta_mm:g} mm" if sta_mm else "no STA"
    print(f"soak: {seconds / 3600:.2f} h of {routine} (seed {seed}) at tracker noise, {skin}, {rate:.0f} Hz, "
          "live loop in 1/30 s batches, nothing slipped" + (f"; monitor {monitor}" if monitor else ""))
    print(f"  false alarms: {n}  ({n / hours:.2f} per hour); suspicions put to the confirming test: "
          f"{replay.monitor.confirmations} ({replay.monitor.confirmations / seconds:.2f}/s)")
    for e in replay.events[:10]:
        print("  ", e.to_dict())
    print(f"  processed at {seconds / took:.1f}x real time ({seconds * rate / took:,.0f} frames/s incl. simulation and re-fits)",
          flush=True)


def fresh_takes(count: int, seconds: float, rate: float, routine: str, sta_mm: float, first_seed: int = 1000,
                monitor: dict | None = None, catch_up: int = 1) -> None:
    """False alarms over `count` takes of `seconds`, each a new performer (seed) doing the routine once
    from the start, as kiosk guests do: every pose is a first visit, which the hour-long soak, looping
    through the same poses, hardly has."""
    start = time.perf_counter()
    alarms = []
    confirmations = 0
    for k in range(count):
        perf = Performer("human", routine=routine, seed=first_seed + k, noise="tracker", rate_hz=rate,
                         seconds=seconds, sta_mm=sta_mm)
        replay = SlipWatch(tree(perf.model), perf.n_sensors, rate, perf.names, **(monitor or {}))
        replay.feed(*frames(perf, rate, 0.0, seconds), catch_up=catch_up)
        alarms += [(first_seed + k, e.sensor, round(e.time_s, 2), round(e.jump_mm, 1)) for e in replay.events]
        confirmations += replay.monitor.confirmations
    took = time.perf_counter() - start
    skin = f"STA {sta_mm:g} mm" if sta_mm else "no STA"
    hours = count * seconds / 3600
    print(f"fresh takes: {count} performers x {seconds:g} s of {routine} from the start ({hours:.2f} h), {skin}, "
          f"{rate:.0f} Hz, live loop" + (f" {catch_up}x behind" if catch_up > 1 else "") + ", nothing slipped"
          + (f"; monitor {monitor}" if monitor else ""))
    print(f"  false alarms: {len(alarms)} ({len(alarms) / hours:.2f} per hour of takes); confirming tests: {confirmations}")
    for a in alarms[:10]:
        print("   (seed, sensor, time_s, jump_mm):", a)
    print(f"  ({took:.1f} s)", flush=True)


def monitor_options(items: list[str]) -> dict:
    """`--monitor KEY=VALUE` options as SlipMonitor keywords: a number, or a tuple written A,B."""
    return {k: tuple(float(x) for x in v.split(",")) if "," in v else float(v)
            for k, v in (o.split("=", 1) for o in items)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--phases", metavar="SENSOR", help="slip only SENSOR, at many moments of one performance (--seed)")
    ap.add_argument("--between", default="20:60", metavar="START:STOP", help="--phases: the span of moments, s")
    ap.add_argument("--moments", type=int, default=40, help="--phases: how many")
    ap.add_argument("--hours", type=float, default=1.0)
    ap.add_argument("--rate", type=float, default=100.0)
    ap.add_argument("--distance", type=float, default=0.02)
    ap.add_argument("--follow", type=float, default=1.0, help="seconds watched after each slip")
    ap.add_argument("--routine", default="walk", help="motion for the detection trials and the soak")
    ap.add_argument("--seed", type=int, default=11, help="performer seed for the soak")
    ap.add_argument("--sta-mm", type=float, default=0.0, help="soft-tissue artefact of the simulated skin (0 = none)")
    ap.add_argument("--fresh", type=int, default=0, metavar="N",
                    help="instead: N takes of --take-s seconds of --routine, each a new performer from the start")
    ap.add_argument("--take-s", type=float, default=30.0)
    ap.add_argument("--catch-up", type=int, default=1,
                    help="--fresh: feed the loop as a service that has fallen behind does (10: 1/3 s micro-batches)")
    ap.add_argument("--sta-suite", action="store_true",
                    help="the STA runs: detection during walk and exercise with 12 mm STA, an --hours soak of "
                    "each of exercise, walk and kiosk with it, and --hours x 120 kiosk guests of 30 s")
    ap.add_argument("--monitor", action="append", default=[], metavar="KEY=VALUE",
                    help="--phases, the soaks and --fresh: a SlipMonitor option other than its default (e.g. "
                    "confirm_s=0.4; a tuple as A,B)")
    ap.add_argument("--tree-seeds", type=int, nargs="+", metavar="SEED",
                    help="instead: the searched tree after a slip of each sensor, these seeds (100 Hz)")
    args = ap.parse_args()
    if args.tree_seeds:
        tree_after_slips(args.tree_seeds)
        return
    monitor = monitor_options(args.monitor)
    if args.phases:
        lo, hi = (float(x) for x in args.between.split(":"))
        phases(args.phases, args.seed, args.rate, args.routine, args.sta_mm, lo, hi, args.moments, args.distance,
               args.follow, monitor)
        return
    if args.fresh:
        fresh_takes(args.fresh, args.take_s, args.rate, args.routine, args.sta_mm, monitor=monitor,
                    catch_up=args.catch_up)
        return
    if args.sta_suite:
        for routine in ("walk", "exercise"):
            detection(args.seeds, args.rate, args.distance, args.follow, routine, sta_mm=12.0)
        for routine in ("exercise", "walk", "kiosk"):
            soak(args.hours, args.rate, routine, args.seed, sta_mm=12.0, monitor=monitor)
        fresh_takes(int(round(args.hours * 120)), 30.0, args.rate, "kiosk", 12.0, monitor=monitor)
        return
    if args.seeds > 0:
        detection(args.seeds, args.rate, args.distance, args.follow, args.routine, args.sta_mm)
    if args.hours > 0:
        soak(args.hours, args.rate, args.routine, args.seed, sta_mm=args.sta_mm, monitor=monitor)


if __name__ == "__main__":
    main()
