"""Slips at every moment of a performance: each of the 16 sensors slipped at many moments of the
exercise, walk and kiosk routines over several seeds, with the simulator's soft tissue, through the live
slip loop (`SlipWatch` in 1/30 s micro-batches, as the service feeds it). Prints the share found and
named right within 0.5 s and 1 s, the misses and wrong names, per routine and overall (issue #32).

    python benchmarks/bench_slip_sweep.py                                  # 3 routines x 3 seeds x 40 moments x 16
    python benchmarks/bench_slip_sweep.py --routines kiosk --seeds 21 --moments 10 --jobs 1
    python benchmarks/bench_slip_sweep.py --monitor confirm_s=0.6          # a SlipMonitor option changed

Each moment's slip is replayed on a copy of the loop fed up to that moment (nothing slipped before it),
watched in 0.1 s steps until the first event or `--follow` seconds.
"""

from __future__ import annotations

import argparse
import copy
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from flockcal.simulator.performer import Performer
from flockcal.solver.slippage.watch import SlipWatch

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # the scoring rule is the tests'
from bench_slippage import frames, monitor_options, tree  # noqa: E402
from slip_scoring import attributes_slip_to  # noqa: E402


def one_performance(routine: str, seed: int, moments: list[float], rate: float, sta_mm: float, distance: float,
                    follow_s: float, sensors: list[str] | None, monitor: dict) -> dict:
    """Every sensor slipped at every moment of one performance; rows (moment, sensor, delay or inf,
    first event's sensor or None), and the false alarms of the untouched loop up to the last moment."""
    perf = Performer("human", routine=routine, seed=seed, noise="tracker", rate_hz=rate, sta_mm=sta_mm)
    base = SlipWatch(tree(perf.model), perf.n_sensors, rate, perf.names, **monitor)
    names = sensors or list(perf.names)
    rows, fed = [], 0.0
    for at in moments:
        perf.clear_faults()
        base.feed(*frames(perf, rate, fed, at))
        fed = at
        for name in names:
            replay = copy.deepcopy(base)
            perf.clear_faults()
            perf.inject_slip(name, distance, at_time=at)
            first, t = None, at
            while first is None and t < at + follow_s - 1e-9:
                t1 = min(at + follow_s, t + 0.1)
                found = replay.feed(*frames(perf, rate, t, t1))
                t = t1
                first = found[0] if found else None
            if first is None:
                rows.append((at, name, float("inf"), None))
            elif attributes_slip_to(first, name, perf.model.names, perf.model.parent):
                rows.append((at, name, float(first.detected_s - at), first.sensor))
            else:
                rows.append((at, name, float("inf"), first.sensor))
    perf.clear_faults()
    alarms = [(round(e.time_s, 2), e.sensor) for e in base.events]
    return {"routine": routine, "seed": seed, "rows": rows, "alarms": alarms}


def report(results: list[dict], label: str) -> None:
    rows = [r for res in results for r in res["rows"]]
    if not rows:
        return
    d = np.array([r[2] for r in rows])
    n = len(d)
    wrong = [r for r in rows if r[3] is not None and not np.isfinite(r[2])]
    fin = d[np.isfinite(d)]
    med = f"{np.median(fin):.2f}" if len(fin) else "nan"
    print(f"  {label}: {n} slips; within 0.5 s {(d <= 0.5).sum()} ({100 * (d <= 0.5).mean():.1f} %), "
          f"within 1 s {(d <= 1.0).sum()} ({100 * (d <= 1.0).mean():.1f} %); median delay {med} s; "
          f"named wrong first {len(wrong)}; false alarms before the slips {sum(len(r['alarms']) for r in results)}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--routines", nargs="+", default=["exercise", "walk", "kiosk"])
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--moments", type=int, default=40)
    ap.add_argument("--between", default="12:62", metavar="START:STOP", help="the span of the moments, s")
    ap.add_argument("--sensors", nargs="+", help="default: all 16")
    ap.add_argument("--rate", type=float, default=144.0, help="the service's default rate")
    ap.add_argument("--sta-mm", type=float, default=12.0, help="the simulator's default soft tissue")
    ap.add_argument("--distance", type=float, default=0.02)
    ap.add_argument("--follow", type=float, default=1.0)
    ap.add_argument("--jobs", type=int, default=2, help="processes (one performance each)")
    ap.add_argument("--monitor", action="append", default=[], metavar="KEY=VALUE",
                    help="a SlipMonitor option other than its default (a tuple as A,B)")
    ap.add_argument("--list", action="store_true", help="print every late, missed or wrongly named slip")
    args = ap.parse_args()
    lo, hi = (float(x) for x in args.between.split(":"))
    moments = [float(x) for x in np.round(np.linspace(lo, hi, args.moments), 3)]
    monitor = monitor_options(args.monitor)
    jobs = [(r, s) for r in args.routines for s in args.seeds]
    print(f"sweep: {len(args.sensors or range(16))} sensors x {len(moments)} moments of {lo:g}-{hi:g} s x "
          f"{len(args.seeds)} seeds x {', '.join(args.routines)}; {args.distance * 100:g} cm slips, STA {args.sta_mm:g} mm, "
          f"{args.rate:g} Hz, watched {args.follow:g} s" + (f"; monitor {monitor}" if monitor else ""), flush=True)
    start = time.perf_counter()
    with ProcessPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        futures = [pool.submit(one_performance, r, s, moments, args.rate, args.sta_mm, args.distance, args.follow,
                               args.sensors, monitor) for r, s in jobs]
        results = [f.result() for f in futures]
    for routine in args.routines:
        report([r for r in results if r["routine"] == routine], routine)
    report(results, "all")
    if args.list:
        for res in results:
            for at, name, delay, named in res["rows"]:
                if delay > 0.5:
                    print(f"    {res['routine']} seed {res['seed']} {name} at {at:g} s: "
                          + (f"{delay:.2f} s" if np.isfinite(delay) else "missed" if named is None else f"named {named}"))
            for a in res["alarms"]:
                print(f"    {res['routine']} seed {res['seed']} false alarm before the slips: {a}")
    print(f"  ({time.perf_counter() - start:.0f} s)")


if __name__ == "__main__":
    main()
