"""Driver throughput: serial bytes → decoded, assembled frames → Gram accumulator, against real time.

The tracker's real-time rate is 16 birds at 144 Hz (2304 records/s); design.md §6 asks for ≥ 20× on
one core. Run: python benchmarks/bench_driver.py [--seconds 30] [--chunk 512] [--take-every 8] [--repeat 3]
[--per-port]

Reads are framed as they come; poses are decoded when frames are taken (the live reader takes them every
20 ms, a few reads' worth), so --take-every 1 is the worst case: a decode after every read. The machine
is shared, so each figure is the best of --repeat runs (the one least disturbed by other jobs).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from flockcal.drivers.records import encode_records, record_length
from flockcal.rotations import from_euler
from flockcal.drivers.assembly import FrameAssembler
from flockcal.drivers.link import FlockSetup
from flockcal.solver.accumulator import GramAccumulator


def stream_bytes(fmt: str, m: int, n: int, rate: float, group: bool) -> bytes:
    t = np.arange(n)[:, None] / rate
    ang = 0.7 * np.sin(2 * np.pi * 0.5 * t + np.arange(m))
    R = from_euler(ang, 0.5 * ang, -ang)
    z = np.zeros((n, m))
    p = np.stack([0.4 + 0.2 * np.sin(t + np.arange(m)), 0.2 * np.cos(t) + z, 0.1 * np.sin(2 * t) + z], -1)
    addresses = np.tile(np.arange(1, m + 1), n) if group else None
    return encode_records(fmt, R.reshape(-1, 3, 3), p.reshape(-1, 3), addresses=addresses)


def bench(fmt: str, m: int, rate: float, seconds: float, chunk: int, take_every: int = 8) -> tuple[float, float]:
    n = int(rate * seconds)
    data = stream_bytes(fmt, m, n, rate, group=True)
    setup = FlockSetup(urls=["bench"], birds=m, addresses=list(range(1, m + 1)), group=True, mode="stream",
                       record_format=fmt, scale_inches=36.0, rate_hz=rate, hemisphere="forward", baud=115200)
    dt_chunk = chunk / (len(data) / seconds)
    reads = ([(0, k * dt_chunk, data[i:i + chunk])] for k, i in enumerate(range(0, len(data), chunk)))
    return _run(FrameAssembler(setup), m, n, reads, take_every)


def bench_ports(fmt: str, m: int, rate: float, seconds: float, take_every: int = 8) -> tuple[float, float]:
    """One port per bird, one record per read (the worst case for per-read cost): 16 interleaved ports."""
    n = int(rate * seconds)
    per_bird = [stream_bytes(fmt, 1, n, rate, group=False) for _ in range(m)]
    L = record_length(fmt, group=False)
    setup = FlockSetup(urls=[f"bench{b}" for b in range(m)], birds=m, addresses=list(range(1, m + 1)), group=False,
                       mode="stream", record_format=fmt, scale_inches=36.0, rate_hz=rate, hemisphere="forward",
                       baud=115200)
    reads = ([(b, k / rate + 0.0005, per_bird[b][k * L:(k + 1) * L]) for b in range(m)] for k in range(n))
    return _run(FrameAssembler(setup), m, n, reads, take_every)


def _run(asm: FrameAssembler, m: int, n: int, reads, take_every: int) -> tuple[float, float]:
    """Feed `reads` (per step: a list of (port, arrival time, bytes)) into `asm`, taking frames into an
    accumulator every `take_every` steps as the reader hands batches over; (bird-records/s, seconds)."""
    acc = GramAccumulator(m)
    t0 = time.perf_counter()
    frames = 0
    for k, step in enumerate(reads):
        for port, t, data in step:
            asm.feed(port, t, data)
        if k % take_every == take_every - 1:
            f = asm.take()
            if len(f):
                acc.update(f.rotations, f.positions, f.valid)
                frames += len(f)
    asm.flush()
    f = asm.take()
    acc.update(f.rotations, f.positions, f.valid)
    frames += len(f)
    elapsed = time.perf_counter() - t0
    assert frames == n, (frames, n)
    return frames * m / elapsed, elapsed


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seconds", type=float, default=30.0, help="seconds of tracker data to push through")
    ap.add_argument("--chunk", type=int, default=512, help="bytes per serial read")
    ap.add_argument("--take-every", type=int, default=8, help="reads between taking frames into the accumulator")
    ap.add_argument("--repeat", type=int, default=3, help="runs per format; the best is printed")
    ap.add_argument("--per-port", action="store_true",
                    help="one port per bird, one record per read (--chunk ignored; frames taken every "
                         "--take-every cycles)")
    args = ap.parse_args()
    m, rate = 16, 144.0
    realtime = m * rate
    print(f"real time: {m} birds at {rate:g} Hz = {realtime:.0f} records/s; target ≥ 20×")
    for fmt in ("position_quaternion", "position_matrix", "position_angles"):
        if args.per_port:
            rps, el = max(bench_ports(fmt, m, rate, args.seconds, args.take_every) for _ in range(args.repeat))
            how = f"{m} ports, one record per read, frames taken every {args.take_every} cycles"
        else:
            rps, el = max(bench(fmt, m, rate, args.seconds, args.chunk, args.take_every) for _ in range(args.repeat))
            how = f"{args.chunk} B reads, frames taken every {args.take_every} reads"
        print(f"{fmt:22s} {rps:10.0f} records/s  {rps / realtime:6.1f}× real time  "
              f"({args.seconds:g} s of data in {el:.2f} s, {how})")


if __name__ == "__main__":
    main()
