"""What the live humanoid streams (VRPN, VMC; server/outputs.py) cost, in process, where a shared machine's load
moves the figure less than a whole service's (bench_server.py --streams-paired measures the service itself): CPU
time of the fc-outputs thread, of the feeding thread inside `Outputs.feed` (the reader's side: a queue append)
and inside `Outputs.hand_over` (the pipeline's side: the streams' work), as % of one core, while `Outputs` is fed
16 birds at 144 Hz in the reader's 5 ms hand-overs, in real time, from the simulated performer's noisy poses
through a fit of them that carries its humanoid, as the service's fits do; the same for VMC alone (60 Hz), VMC
with VRPN's own client over UDP, and over TCP. The feeding thread plays the pipeline's too: it hands over to the
streams after each batch and when the time the last hand-over asked for comes, as `Pipeline._run` does.

    python benchmarks/bench_streams.py [--seconds 20]

Needs VRPN's client at ../shared/tools/vrpn/vrpn_print_devices (beside the repository). Asserts nothing. The
figures run higher than the service's (bench_server.py): the feeding thread here shares the interpreter with
the streams' thread.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # as `flockcal serve` runs BLAS (set before numpy loads)

import numpy as np  # noqa: E402

from flockcal.clock import SYSTEM  # noqa: E402
from flockcal.frames import Frames  # noqa: E402
from flockcal.server.outputs import Outputs  # noqa: E402
from flockcal.server.settings import Settings  # noqa: E402
from flockcal.simulator.body import HUMAN_PARENTS  # noqa: E402
from flockcal.simulator.performer import Performer  # noqa: E402
from flockcal.solver.accumulator import GramAccumulator  # noqa: E402
from flockcal.solver.calibration import calibrate  # noqa: E402
from flockcal.solver.humanoid import find_humanoid  # noqa: E402

RATE = 144.0
PRINT_DEVICES = Path(__file__).resolve().parents[1].parent / "shared" / "tools" / "vrpn" / "vrpn_print_devices"


class Snapshot:
    """What the outputs read of the pipeline's snapshots: a stopped session's fit, no session live."""

    def __init__(self, fit):
        self.pose_fit, self.pose_fit_id, self.session = fit, ("bench", None), None


def thread_cpu(native_id: int) -> float:
    """CPU seconds of a thread of this process from the scheduler's own count (schedstat: nanoseconds run),
    not /proc's stat, whose clock-tick samples over-count a thread that wakes on timers."""
    with open(f"/proc/self/task/{native_id}/schedstat") as fh:
        return int(fh.read().split()[0]) / 1e9


def run(mode: str, seconds: float, fit, names, R, x, v, t) -> dict:
    drain = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    drain.bind(("127.0.0.1", 0))
    threading.Thread(target=lambda: _drain(drain), daemon=True).start()
    settings = Settings(vrpn_port=0 if mode != "vmc" else None, osc_targets=(f"127.0.0.1:{drain.getsockname()[1]}",),
                        data_dir=Path(tempfile.gettempdir()))
    out = Outputs(settings, names, lambda: Snapshot(fit), SYSTEM)
    out.start()
    client = None
    if mode != "vmc":
        device = f"flockcal@127.0.0.1:{out.vrpn.port}" if mode == "udp" else f"flockcal@tcp://127.0.0.1:{out.vrpn.port}"
        client = subprocess.Popen([str(PRINT_DEVICES), device], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        tid = next(th.native_id for th in threading.enumerate() if th.name == "flockcal-outputs")
        start, fed, c0, in_feed, in_hand, again, f = SYSTEM.monotonic(), 0, None, 0.0, 0.0, np.inf, None
        total = int(seconds * RATE) + int(2 * RATE)  # 2 s to settle (the client connects), then the window
        while fed < total:
            due = min(total, int((SYSTEM.monotonic() - start) * RATE))
            if due > fed:
                f = Frames(t[fed:due] - t[0] + start, R[fed:due], x[fed:due], v[fed:due])
                before = time.thread_time()
                out.feed(f)
                in_feed += time.thread_time() - before
                fed = due
            # This thread is the pipeline's too: it hands over to the streams at each step (a batch came, or
            # the time the last hand-over asked for has).
            if f is not None or SYSTEM.monotonic() >= again:
                before = time.thread_time()
                again = out.hand_over()
                in_hand += time.thread_time() - before
            f = None
            if c0 is None and fed >= 2 * RATE:
                c0, w0, r0 = thread_cpu(tid), time.monotonic(), (out.vrpn.reports if out.vrpn else 0)
                in_feed = in_hand = 0.0
            time.sleep(0.005)
        c1, w1, r1 = thread_cpu(tid), time.monotonic(), (out.vrpn.reports if out.vrpn else 0)
        st = out.status()
    finally:
        if client is not None:
            client.terminate()
            client.wait(10)
        out.stop()
        drain.close()
    return {"cpu": 100 * (c1 - c0) / (w1 - w0), "feed": 100 * in_feed / (w1 - w0),
            "hand": 100 * in_hand / (w1 - w0), "reports_hz": (r1 - r0) / (w1 - w0),
            "clients": len(st["vrpn"]["clients"]) if st["vrpn"] else 0, "bundles": st["vmc"]["bundles_sent"]}


def _drain(sock: socket.socket) -> None:
    while True:
        try:
            sock.recv(65536)
        except OSError:
            return


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=20.0, help="length of each measured window")
    args = ap.parse_args(argv)
    if not PRINT_DEVICES.exists():
        print(f"bench_streams: VRPN's client is not at {PRINT_DEVICES}", file=sys.stderr)
        return 2
    p = Performer("human", "exercise", seed=1, rate_hz=RATE)
    t = np.arange(0, args.seconds + 5, 1 / RATE)
    R, x, v = p.poses(t)
    acc = GramAccumulator(p.n_sensors)
    acc.add_poses(R, x, v)
    fit = calibrate(acc, hierarchy=HUMAN_PARENTS, root="pelvis", names=p.names)
    # The humanoid, as the service's fits carry it (found from a sample of the take, one frame every 0.1 s):
    # without it the streams find none from their first frames and send no bones, which costs nothing.
    every = t[::int(RATE / 10)].size
    fit = dataclasses.replace(fit, humanoid=find_humanoid(fit, R[::int(RATE / 10)], x[::int(RATE / 10)],
                                                          v[::int(RATE / 10)]))
    if not fit.humanoid.posable:
        print(f"bench_streams: no humanoid found from {every} frames: {fit.humanoid.reason}", file=sys.stderr)
        return 2
    print(f"the streams (fc-outputs, the reader's side in feed, the pipeline's in hand_over), 16 birds at {RATE:g} Hz fed in real time, {args.seconds:g} s windows")
    for mode, what in (("vmc", "VMC at 60 Hz alone"), ("udp", "VMC + VRPN, vrpn_print_devices over UDP"),
                       ("tcp", "VMC + VRPN, vrpn_print_devices over TCP")):
        w = run(mode, args.seconds, fit, p.names, R, x, v, t)
        print(f"  {what:42s} {w['cpu'] + w['feed'] + w['hand']:5.2f} % of one core: fc-outputs {w['cpu']:5.2f}, "
              f"in feed {w['feed']:5.2f}, in hand_over {w['hand']:5.2f}   (VRPN frames {w['reports_hz']:5.1f}/s to "
              f"{w['clients']} client(s); load {os.getloadavg()[0]:.1f})", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
