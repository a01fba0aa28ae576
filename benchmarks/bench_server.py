"""End-to-end latency and CPU use of `flockcal serve` with 16 birds at 144 Hz on a fake tracker (pty).

Latency: from the moment the fake tracker's clock reaches a sample (its record leaves within one 2 ms
pump tick) to the websocket client receiving the first snapshot whose pose shows that sample. The
sample time is encoded in sensor 0's x position (a 6 s sawtooth the whole body follows), so nothing
but the wire format carries it. CPU: user+system time of the service process over the window, as % of
one core, and per named thread. One window per probe rate: by default a dashboard's 15 Hz, then every
snapshot. Targets (issue 5): p99 < 50 ms, CPU < 25 % of one core.

    python benchmarks/bench_server.py [--seconds 20] [--dashboards 0] [--probe-hz 15 1000]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import multiprocessing
import os
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import httpx
import numpy as np
import websockets

from flockcal.simulator.performer import Performer
from flockcal.simulator.pty_tracker import PtyTracker

# The service runner is a test helper (it needs httpx, a test-only extra): it lives in tests/.
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from server_helpers import ServerProcess, free_port, wait_connected  # noqa: E402

RATE = 144.0
SAW_S, SLOPE, X0 = 6.0, 0.1, 0.2  # sensor 0 x = X0 + SLOPE * (t mod SAW_S)


class MarkedSource:
    """A performer whose sensor 0 carries the sample time in its x coordinate.

    The whole body is shifted along x, every sensor by the same amount, so that sensor 0 lands on the
    sawtooth: joints stay joints (a common translation cancels in every pair's residual) and the
    slip monitor sees no slip. Overwriting sensor 0 alone would tear its joints apart at every wrap.
    """

    def __init__(self, performer: Performer):
        self.p = performer
        self.names = performer.names
        self.n_sensors = performer.n_sensors
        self.full_scale_in = performer.full_scale_in

    def poses(self, times):
        R, x, v = self.p.poses(times)
        shift = X0 + SLOPE * np.mod(np.asarray(times, dtype=float), SAW_S) - x[..., 0, 0]
        x = x.copy()
        x[..., 0] += shift[..., None]
        return R, x, v


def thread_cpu(pid: int) -> dict[str, float]:
    """CPU seconds per thread name (reader, pipeline, fit, event loop…) of the service process."""
    out: dict[str, float] = {}
    for tid in os.listdir(f"/proc/{pid}/task"):
        try:
            with open(f"/proc/{pid}/task/{tid}/comm") as fh:
                name = fh.read().strip()
            with open(f"/proc/{pid}/task/{tid}/stat") as fh:
                fields = fh.read().rsplit(")", 1)[1].split()
        except OSError:
            continue
        out[name] = out.get(name, 0.0) + (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    return out


def cpu_seconds(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as fh:
        fields = fh.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


async def measure(url: str, clock_t0: float, seconds: float, dashboards: int, probe_hz: float) -> tuple[list[float], float]:
    latencies = []
    granted = [probe_hz]

    async def dashboard():
        async with websockets.connect(url) as ws:
            await ws.send(json.dumps({"type": "subscribe", "rate_hz": 15,
                                      "content": ["status", "fit", "residuals", "events", "pose"]}))
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                try:
                    await asyncio.wait_for(ws.recv(), 1)
                except asyncio.TimeoutError:
                    pass

    async def probe():
        async with websockets.connect(url) as ws:
            await ws.send(json.dumps({"type": "subscribe", "rate_hz": probe_hz, "content": ["pose"]}))
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                msg = json.loads(await ws.recv())
                now = time.monotonic()
                if msg.get("type") == "subscribed":
                    granted[0] = msg["rate_hz"]
                if msg.get("type") != "pose" or not msg["pose"]:
                    continue
                x = msg["pose"]["sensors"][0]["p"][0]
                elapsed = now - clock_t0
                phase = (x - X0) / SLOPE
                k = np.round((elapsed - phase) / SAW_S)
                latencies.append(elapsed - (k * SAW_S + phase))

    await asyncio.gather(probe(), *[dashboard() for _ in range(dashboards)])
    return latencies, granted[0]


def measure_apart(*args) -> tuple[list[float], float]:
    """`measure` in a process of its own: in this one the fake tracker's thread would hold the GIL
    while the probe's message waits, and that delay is the benchmark's, not the service's."""
    with ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn")) as pool:
        return pool.submit(_measure_sync, *args).result()


def _measure_sync(*args) -> tuple[list[float], float]:
    return asyncio.run(measure(*args))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=20.0, help="length of each measured window")
    ap.add_argument("--dashboards", type=int, default=0, help="extra dashboard-like websocket clients")
    ap.add_argument("--probe-hz", type=float, nargs="+", default=[15.0, 1000.0],
                    help="rate(s) the latency probe subscribes at, one window each (default: 15, a dashboard's "
                         "rate, then 1000: every snapshot the service publishes)")
    args = ap.parse_args(argv)

    performer = Performer("human", "exercise", seed=1, rate_hz=RATE)
    pty = PtyTracker(MarkedSource(performer), birds=16, baud=921600, rate_hz=RATE).start()
    clock_t0 = pty.flock.clock._t0
    data = tempfile.mkdtemp(prefix="flockcal-bench-")
    port = free_port()
    proc = ServerProcess(["--device", pty.device, "--birds", "16", "--fast-init", "--scale", "72", "--baud", "921600", "--data-dir", data,
                          "--names", ",".join(performer.names)], port, log_path=os.path.join(data, "serve.log"))
    try:
        proc.start()
        wait_connected(proc.url, frames=int(RATE))
        httpx.post(proc.url + "/api/sessions", json={"performer": "bench"}).raise_for_status()
        time.sleep(3.0)  # let the fit settle into its steady state
        url = proc.url.replace("http://", "ws://") + "/ws/live"
        for probe_hz in args.probe_hz:
            window(proc, url, clock_t0, args.seconds, args.dashboards, probe_hz)
    finally:
        proc.stop()
        pty.stop()
    return 0


def window(proc: ServerProcess, url: str, clock_t0: float, seconds: float, dashboards: int, probe_hz: float) -> None:
    """Measure and print one window: latency at the probe, CPU of the service process and its threads."""
    st0 = httpx.get(proc.url + "/api/status").json()
    cpu0, wall0, threads0 = cpu_seconds(proc.proc.pid), time.monotonic(), thread_cpu(proc.proc.pid)
    lat, probe_rate = measure_apart(url, clock_t0, seconds, dashboards, probe_hz)
    lat = np.array(lat) * 1000
    cpu1, wall1, threads1 = cpu_seconds(proc.proc.pid), time.monotonic(), thread_cpu(proc.proc.pid)
    st1 = httpx.get(proc.url + "/api/status").json()
    session = st1["session"]["id"]
    slips = [e for e in httpx.get(f"{proc.url}/api/sessions/{session}/events").json()["events"]
             if e["type"] == "slip"]
    cpu = 100 * (cpu1 - cpu0) / (wall1 - wall0)
    frames_hz = (st1["frames"] - st0["frames"]) / (wall1 - wall0)
    fits_hz = (st1["fits"] - st0["fits"]) / (wall1 - wall0)
    p50, p99 = np.percentile(lat, [50, 99])
    print(f"flockcal serve, 16 birds at {RATE:g} Hz on a pty, {seconds:g} s, {dashboards} extra dashboards, "
          f"latency probe subscribed at {probe_rate:g} Hz (in its own process)")
    print(f"  frames received     {frames_hz:8.1f} /s   (dropped records in the window: {st1['dropped_records'] - st0['dropped_records']})")
    print(f"  full refits         {fits_hz:8.1f} /s   (target >= 30; {st1['fit_ms']} ms each)")
    print(f"  slip alarms         {len(slips):8d}     (none expected: the performer's sensors stay put)")
    print(f"  latency samples     {len(lat):8d}")
    print(f"  latency p50         {p50:8.1f} ms")
    print(f"  latency p99         {p99:8.1f} ms   (target < 50 ms: {50 / p99:.2f}x margin)")
    print(f"  latency max         {lat.max():8.1f} ms")
    print(f"  service CPU         {cpu:8.1f} % of one core   (target < 25 %: {25 / cpu:.2f}x margin)")
    for name in sorted(threads1, key=lambda k: threads0.get(k, 0.0) - threads1[k]):
        share = 100 * (threads1[name] - threads0.get(name, 0.0)) / (wall1 - wall0)
        if share >= 0.5:
            print(f"    thread {name:18s} {share:5.1f} %")
    print(f"  load average        {os.getloadavg()[0]:8.2f}   (on {os.cpu_count()} cores; other work inflates the latency)")


if __name__ == "__main__":
    sys.exit(main())
