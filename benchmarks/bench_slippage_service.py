"""Slip detection delays measured through the live service, as an operator meets them: a real
`flockcal serve` on the built-in simulator, a session started over REST with automatic topology (no
hierarchy), 2 cm slips of every sensor in turn through `POST /api/simulator/slip` from 20 s on, and the
events read on the websocket. Prints, per soft-tissue setting, median / p95 / worst of the delay from
the slip's sample time to the event's arrival at the client and to the event's own `detected_s`, and
the attributions.

    python benchmarks/bench_slippage_service.py                    # 3 trials × 16 sensors, 12 mm STA and rigid
    python benchmarks/bench_slippage_service.py --trials 1 --sta-mm 12 --sensors head r_shin
    python benchmarks/bench_slippage_service.py --trials 1 --first-seed 2 --routine walk --logs /tmp/logs
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

# The service runner and the operator's client are test helpers (httpx is a test-only extra): tests/.
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from server_helpers import ServerProcess, free_port, wait_connected  # noqa: E402
from slip_service import human_tree, run, spread_order  # noqa: E402


def device(seed: int, sta_mm: float, routine: str, rate: float) -> str:
    return f"sim://?birds=16&motion={routine}&rate={rate:g}&baud=921600&seed={seed}&sta_mm={sta_mm:g}"


def figures(values) -> str:
    v = np.asarray(values, dtype=float)
    if not len(v):
        return "none"
    return f"median {np.median(v):.2f} s, p95 {np.percentile(v, 95):.2f} s, worst {v.max():.2f} s"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--trials", type=int, default=3, help="fresh services (simulator seeds) per STA setting")
    ap.add_argument("--first-seed", type=int, default=1, help="simulator seed of the first trial (then +1 each)")
    ap.add_argument("--sta-mm", type=float, nargs="+", default=[12.0, 0.0], help="soft-tissue settings to run")
    ap.add_argument("--routine", default="exercise", help="the simulated performer's routine (the service's default: exercise)")
    ap.add_argument("--rate", type=float, default=144.0, help="measurement rate, Hz (the service's default: 144)")
    ap.add_argument("--sensors", nargs="+", help="sensors to slip (default: all 16, no two neighbours in a row)")
    ap.add_argument("--warmup", type=float, default=20.0, help="session time before the first slip, s")
    ap.add_argument("--spacing", type=float, default=10.0, help="wall time between slips, s")
    ap.add_argument("--distance", type=float, default=0.02, help="slip distance, m")
    ap.add_argument("--logs", type=Path, help="keep each service's log here (tree changes, slip watch restarts)")
    args = ap.parse_args()
    names, parent = human_tree()
    sensors = args.sensors or spread_order(names, parent)
    print(f"{len(sensors)} sensors × {args.trials} trials, {args.distance * 100:g} cm slips {args.spacing:g} s apart "
          f"from {args.warmup:g} s, {args.routine} at {args.rate:g} Hz, automatic topology")
    for sta in args.sta_mm:
        arrival, detected, onset, wrong, missed, found = [], [], [], [], [], 0
        for trial in range(args.trials):
            seed = args.first_seed + trial
            with tempfile.TemporaryDirectory() as tmp:
                port = free_port()
                srv = ServerProcess(["--device", device(seed, sta, args.routine, args.rate), "--data-dir", tmp,
                                     "--fast-init"], port, log_path=Path(tmp) / "serve.log")
                srv.start()
                try:
                    wait_connected(srv.url)
                    t0 = time.monotonic()
                    _, slips, _ = run(srv.url, sensors, warmup_s=args.warmup, spacing_s=args.spacing,
                                      distance_m=args.distance)
                finally:
                    srv.stop()
                    if args.logs:
                        args.logs.mkdir(parents=True, exist_ok=True)
                        (args.logs / f"serve-sta{sta:g}-seed{seed}.log").write_bytes((Path(tmp) / "serve.log").read_bytes())
            for s in slips:
                wrong += [(seed, s.sensor, e.get("sensor"), e.get("candidates")) for e in s.others]
                if s.event is None:
                    missed.append((seed, s.sensor))
                    continue
                found += 1
                arrival.append(s.arrival_s)
                detected.append(s.detected_s)
                onset.append(s.onset_error_s)
            line = ", ".join(f"{s.sensor} {s.detected_s:.2f}/{s.arrival_s:.2f}" if s.event else f"{s.sensor} missed"
                             for s in slips)
            print(f"  STA {sta:g} mm, seed {seed} ({time.monotonic() - t0:.0f} s; detected/arrival s): {line}", flush=True)
        n = args.trials * len(sensors)
        print(f"STA {sta:g} mm: found and attributed {found} / {n}; missed {missed or 'none'}")
        print(f"  sample time → arrival at the client: {figures(arrival)}")
        print(f"  sample time → the event's detected_s: {figures(detected)}")
        print(f"  onset error (time_s − sample time): median {np.median(onset) if onset else float('nan'):+.3f} s")
        print(f"  events blaming another sensor: {len(wrong)} {wrong if wrong else ''}", flush=True)


if __name__ == "__main__":
    main()
