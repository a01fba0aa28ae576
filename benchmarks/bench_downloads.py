"""Memory of `flockcal serve` while clients download a 1-hour session: RSS growth of the service process
during 4 concurrent downloads of each kind (/take, /bvh, /gltf, /skeleton, /raw). Target (issue 16): < 50 MB.

The hour is generated, not recorded: 60 s of the simulated performer (16 birds, 144 Hz) fitted once,
then written to the session's frame log over and over with the clock running on, and a .fobraw of
the same size. The session row is put in the service's database before it starts.

    python benchmarks/bench_downloads.py [--minutes 60] [--clients 4] [--kinds take bvh gltf skeleton raw]
"""

from __future__ import annotations

import argparse
import asyncio
import os
import shutil
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx
import numpy as np

from flockcal.drivers.records import decode_block, encode_records
from flockcal.server.framelog import FrameLog
from flockcal.server.fitting import fit_calibration
from flockcal.solver.accumulator import GramAccumulator
from flockcal.server.store import Store
from flockcal.simulator.performer import Performer

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # the test helpers
from server_helpers import ServerProcess, free_port  # noqa: E402

RATE = 144.0
SID = "20260101-000000-abcdef"


def rss_mb(pid: int) -> float:
    with open(f"/proc/{pid}/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    raise RuntimeError("no VmRSS")


def make_session(data: Path, minutes: float) -> dict:
    performer = Performer("human", "exercise", seed=1, rate_hz=RATE, period=8.0)
    t = np.arange(int(60 * RATE)) / RATE
    R, p, valid = performer.poses(t)
    # As the reader hands them over: the tracker's position/matrix words decoded (the frame log keeps words).
    n, m = valid.shape
    raw = np.frombuffer(encode_records("position_matrix", R.reshape(-1, 3, 3), p.reshape(-1, 3), scale_inches=72),
                        np.uint8).reshape(n * m, -1)
    R, p, ok, _ = decode_block("position_matrix", raw, scale_inches=72)
    R, p, valid = R.reshape(n, m, 3, 3), p.reshape(n, m, 3), valid & ok.reshape(n, m)
    acc = GramAccumulator(performer.n_sensors)
    acc.add_poses(R, p, valid)
    result = fit_calibration(acc, performer.names)[0]
    rec = data / "recordings"
    rec.mkdir(parents=True, exist_ok=True)
    log = FrameLog(rec / f"{SID}.frames", list(performer.names), RATE)
    n_total = int(minutes * 60 * RATE)
    written = 0
    while written < n_total:
        k = min(len(t), n_total - written)
        log.write(written / RATE + t[:k], R[:k], p[:k], valid[:k])
        log.flush()
        written += k
    log.close()
    frames_bytes = (rec / f"{SID}.frames").stat().st_size
    with open(rec / f"{SID}.fobraw", "wb") as fh:  # served as a file: its content does not matter here
        block = os.urandom(1 << 20)
        for _ in range(frames_bytes >> 20):
            fh.write(block)
    store = Store(data / "flockcal.sqlite3")
    store.insert_session({"id": SID, "performer": "Bench", "state": "stopped", "root": result["root"],
                          "hierarchy": None, "names": list(performer.names), "device": "sim://bench",
                          "rate_hz": RATE, "created_at": time.time(), "frames": written,
                          "recording": f"{SID}.frames"})
    store.update_session(SID, result=result)
    store.close()
    return {"frames": written, "frames_mb": frames_bytes / 2**20}


async def download(url: str, path: str) -> int:
    size = 0
    async with httpx.AsyncClient(timeout=None) as client:
        async with client.stream("GET", url + path) as r:
            r.raise_for_status()
            async for chunk in r.aiter_bytes():
                size += len(chunk)
    return size


def measure(srv: ServerProcess, kind: str, clients: int) -> tuple[float, float, float, int]:
    pid = srv.proc.pid
    base = rss_mb(pid)
    peak = [base]
    stop = threading.Event()

    def sample():
        while not stop.is_set():
            peak[0] = max(peak[0], rss_mb(pid))
            time.sleep(0.02)

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    t0 = time.monotonic()

    async def main():
        return await asyncio.gather(*[download(srv.url, f"/api/sessions/{SID}/{kind}") for _ in range(clients)])

    sizes = asyncio.run(main())
    took = time.monotonic() - t0
    stop.set()
    sampler.join()
    return base, peak[0] - base, took, sizes[0]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=60.0)
    ap.add_argument("--clients", type=int, default=4)
    ap.add_argument("--kinds", nargs="+", default=["take", "bvh", "gltf", "skeleton", "raw"])
    args = ap.parse_args()
    data = Path(tempfile.mkdtemp(prefix="flockcal-bench-dl-"))
    try:
        t0 = time.monotonic()
        info = make_session(data, args.minutes)
        print(f"session: {info['frames']} frames ({args.minutes:g} min, 16 birds, {RATE:g} Hz), frame log "
              f"{info['frames_mb']:.0f} MB, made in {time.monotonic() - t0:.0f} s", flush=True)
        port = free_port()
        srv = ServerProcess(["--data-dir", str(data)], port).start()
        try:
            time.sleep(2.0)  # let the service settle (reader, first snapshots) before the baseline
            for kind in args.kinds:
                base, growth, took, size = measure(srv, kind, args.clients)
                print(f"{args.clients} concurrent /{kind}: {size / 2**20:.0f} MB each in {took:.1f} s; RSS "
                      f"{base:.0f} MB -> +{growth:.1f} MB (target < 50 MB: {growth / 50:.2f} of it)", flush=True)
        finally:
            srv.stop()
    finally:
        shutil.rmtree(data, ignore_errors=True)


if __name__ == "__main__":
    main()
