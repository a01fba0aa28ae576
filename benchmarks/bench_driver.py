"""Driver throughput: serial bytes → decoded, assembled frames → Gram accumulator, against real time.

The tracker's real-time rate is 16 birds at 144 Hz (2304 records/s); design.md §6 asks for ≥ 20× on
one core. Run: python benchmarks/bench_driver.py [--seconds 30] [--chunk 512] [--take-every 8] [--repeat 3]
[--per-port] [--decoder] [--pty SECONDS]

Reads are framed as they come; poses are decoded when frames are taken (the live reader takes them every
20 ms, a few reads' worth), so --take-every 1 is the worst case: a decode after every read. The machine
is shared, so each figure is the best of --repeat runs (the one least disturbed by other jobs).
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # one core's figures (set before numpy loads BLAS)

import numpy as np  # noqa: E402

from flockcal.drivers.records import encode_records, record_length  # noqa: E402
from flockcal.drivers.stream import StreamDecoder  # noqa: E402
from flockcal.rotations import from_euler  # noqa: E402
from flockcal.drivers.assembly import FrameAssembler  # noqa: E402
from flockcal.drivers.link import FlockSetup  # noqa: E402
from flockcal.solver.accumulator import GramAccumulator  # noqa: E402


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


def bench_decoder(fmt: str, m: int, records: int, chunk: int) -> tuple[float, float]:
    """The wire format alone: `records` group-mode records of m birds fed to `StreamDecoder.feed` in
    `chunk`-byte reads, as a live reader would; (records/s, seconds) of this process's CPU time, which a
    loaded machine disturbs less than wall time."""
    data = stream_bytes(fmt, m, records // m, 144.0, group=True)
    dec = StreamDecoder(fmt, group=True, n_birds=m)
    t0 = time.process_time()
    got = sum(len(dec.feed(data[i:i + chunk])) for i in range(0, len(data), chunk))
    elapsed = time.process_time() - t0
    assert got == records, (got, records)
    return records / elapsed, elapsed


def bench_pty(seconds: float, m: int = 16, rate: float = 144.0) -> None:
    """A fake flock on m pty ports (one bird each, POS/QUAT, 115200 baud) read by the TrackerReader for
    `seconds`, both in this process: records/s each port delivered, and the CPU both used."""
    import resource
    from collections import Counter

    from flockcal.drivers.link import Timing
    from flockcal.drivers.reader import TrackerConfig, TrackerReader
    from flockcal.simulator.pty_tracker import PtyTracker
    from flockcal.simulator.smooth_source import SmoothSource

    got: list = []  # valid flags of every frame (radius 0.3: the sensors stay at x > 0, no hemisphere flips)
    events: list = []
    with PtyTracker(SmoothSource(m, seed=1, radius=0.3), birds=m, ports=m, baud=115200) as trk:
        cfg = TrackerConfig(urls=trk.devices, birds=m, timing=Timing.fast(), rate_hz=rate,
                            record_format="position_quaternion")
        reader = TrackerReader(cfg, on_frames=lambda f: got.append(f.valid.copy()), on_event=events.append)
        reader.start(wait=15)
        try:
            got.clear()
            events.clear()
            cpu0, t0 = resource.getrusage(resource.RUSAGE_SELF), time.monotonic()
            time.sleep(seconds)
            cpu1, t1 = resource.getrusage(resource.RUSAGE_SELF), time.monotonic()
            valid = np.concatenate(got) if got else np.zeros((0, m), bool)
            during = dict(Counter(e.kind for e in events))
        finally:
            reader.stop()
    per_port = valid.sum(axis=0) / (t1 - t0)
    cpu = (cpu1.ru_utime - cpu0.ru_utime + cpu1.ru_stime - cpu0.ru_stime) / (t1 - t0)
    print(f"{m} pty ports, POS/QUAT at {rate:g} Hz, {seconds:g} s: {per_port.min():.0f}–{per_port.max():.0f} "
          f"records/s per port; the fake tracker and the reader used {100 * cpu:.0f} % of one core; "
          f"load average {os.getloadavg()[0]:.1f}; reader events in the window: {during or 'none'}")


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
                acc.add_poses(f.rotations, f.positions, f.valid)
                frames += len(f)
    asm.flush()
    f = asm.take()
    acc.add_poses(f.rotations, f.positions, f.valid)
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
    ap.add_argument("--decoder", action="store_true",
                    help="the wire format alone: 160,000 records through StreamDecoder.feed in 2 KB reads")
    ap.add_argument("--pty", type=float, metavar="SECONDS",
                    help="instead: 16 pty ports of the fake tracker read by the TrackerReader for SECONDS")
    args = ap.parse_args()
    if args.pty:
        return bench_pty(args.pty)
    m, rate = 16, 144.0
    realtime = m * rate
    print(f"real time: {m} birds at {rate:g} Hz = {realtime:.0f} records/s; target ≥ 20×")
    if args.decoder:
        for fmt in ("position_quaternion", "position_angles", "position_matrix"):
            rps, el = max(bench_decoder(fmt, m, 160_000, 2048) for _ in range(args.repeat))
            print(f"{fmt:22s} {rps:10.0f} records/s  {rps / realtime:6.1f}× real time  (decoder only, "
                  f"160,000 records in 2 KB reads, {el:.2f} s of CPU, best of {args.repeat})")
        return
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
