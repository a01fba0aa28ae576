"""End-to-end latency and CPU use of `flockcal serve` with 16 birds at 144 Hz on a fake tracker (pty).

Latency: from the moment the fake tracker's clock reaches a sample (its record leaves within one 2 ms
pump tick) to the websocket client receiving the first snapshot whose pose shows that sample. The
sample time is encoded in sensor 0's x position (a 6 s sawtooth the whole body follows), so nothing
but the wire format carries it. CPU: user+system time of the service process over the window, as % of
one core, and per named thread. One window per probe rate: by default a dashboard's 15 Hz, then every
snapshot. Targets (issue 5): p99 < 50 ms, CPU < 25 % of one core (issue 33: 15 %).

    python benchmarks/bench_server.py [--seconds 20] [--dashboards 0] [--probe-hz 15 1000]

A/B mode (`--ab REV`): the service of git revision REV and the service of this working tree run in
turn, each on a fresh fake tracker and a fresh service, same settings, `--rounds` times (the order
swaps every round, so a machine that speeds up or slows down during the call favours neither), one
window each at the first `--probe-hz`. REV is exported with `git archive` into a temporary folder
(nothing in the repository or its worktrees changes) and laid out as an importable `flockcal` package
(symlinks mirroring pyproject's package-dir), which goes first on the service's PYTHONPATH; this working
tree is laid out the same way (symlinks into it) for B. Each service runs from its data folder, not the
caller's: `python -m` puts the working folder first on the import path, and from the repository's root
that was this tree's `flockcal/` (with the editable install's parts) on both sides, so every A/B run
before 2026-12-05 compared this tree with itself. Before a side is measured, a child started the same way
prints where it imports `flockcal.server` and `flockcal.solver` from; a side that would run other code
than its own stops the run. The same interpreter and dependencies run both, and this tree's fake
tracker and probe serve both. Printed per
run and as medians: service CPU (% of one core, the service process only), the fake tracker's thread
CPU (in this process) separately, p99 latency, refits/s and slip alarms; then the ratio this tree / REV
of each pair of neighbouring runs, and its median.

    python benchmarks/bench_server.py --ab main --rounds 3 --seconds 30

The live humanoid streams (issue 47): `--streams` runs the service with `--vrpn` and `--osc` and attaches
VRPN's own client (`vrpn_print_devices` from ../shared/tools/vrpn, over its UDP channel, output discarded)
and a VMC receiver (a UDP socket this process drains); `--streams-ab` runs this tree's service in turn
without (A) and with (B) them, as `--ab` does two revisions, and prints what the streams add in points of
one core (B − A per round, neighbouring runs) and their own thread's share (fc-outputs).

    python benchmarks/bench_server.py --streams-ab --rounds 3 --seconds 20

The whole service's CPU moves by several points between runs of the same code on a shared machine (other
work, the refit rate that follows it), more than the streams cost. `--streams-paired` runs A and B at the
same time instead, each with its fake tracker in a process of its own, and reads both processes' CPU
(/proc, user + system) over the same windows: what loads the machine loads both, and each window's B − A is
one paired sample. `--windows` windows of `--seconds` per round, a fresh pair each round (which side starts
first alternates), measured once B's streams send the humanoid's bones to its VRPN client (a session's
first 10-20 s of fits are not human-shaped yet, and streams sending no bones cost less); printed: the median B − A over all windows and per round, the same without the fit
thread (whose CPU follows the refit rate each side got), per thread, and fc-outputs' own share. `--rev REV`
serves git revision REV's code in either streams mode (default: this tree).

    python benchmarks/bench_server.py --streams-paired --rounds 3 --windows 8 --seconds 5
"""

from __future__ import annotations

import argparse
import asyncio
import json
import multiprocessing
import os
import shutil
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import httpx
import numpy as np
import websockets

from flockcal.clock import SYSTEM
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
                now = SYSTEM.monotonic()  # the fake tracker's clock, the same in every process (the boot clock)
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
    ap.add_argument("--ab", metavar="REV", help="A/B mode: the service of git revision REV against this tree's, in turn")
    ap.add_argument("--rounds", type=int, default=3, help="A/B mode: runs of each side (default 3)")
    ap.add_argument("--streams", action="store_true",
                    help="serve VRPN and VMC with a VRPN client and a VMC receiver attached")
    ap.add_argument("--streams-ab", action="store_true",
                    help="A/B mode for the streams: this tree without them (A) and with them and their clients (B)")
    ap.add_argument("--streams-paired", action="store_true",
                    help="the streams' A and B at the same time, CPU of both read over the same windows")
    ap.add_argument("--windows", type=int, default=8, help="--streams-paired: windows per round (default 8)")
    ap.add_argument("--rev", help="--streams-ab / --streams-paired: serve git revision REV (default: this tree)")
    args = ap.parse_args(argv)
    if args.ab:
        return ab(args.ab, args.rounds, args.seconds, args.dashboards, args.probe_hz[0])
    if args.streams_ab:
        return streams_ab(args.rounds, args.seconds, args.dashboards, args.probe_hz[0], args.rev)
    if args.streams_paired:
        return streams_paired(args.rounds, args.windows, args.seconds, args.rev)

    tmp = tempfile.mkdtemp(prefix="flockcal-bench-site-")
    try:  # this tree's code, as B runs it in A/B mode, not whatever the editable install points at
        with Service(tree_site(tmp), streams=args.streams) as svc:
            for probe_hz in args.probe_hz:
                window(svc, args.seconds, args.dashboards, probe_hz)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return 0


class Service:
    """A fake tracker on a pty (a thread of this process) and a `flockcal serve` reading it, with a live
    session settled into its steady state, serving the code of `site` (`tree_site`, `export_revision`), which
    goes first on the service's PYTHONPATH."""

    def __init__(self, site: str, streams: bool = False):
        self.site = site
        self.streams = streams
        self.attached: list = []

    def __enter__(self) -> "Service":
        performer = Performer("human", "exercise", seed=1, rate_hz=RATE)
        self.pty = PtyTracker(MarkedSource(performer), birds=16, baud=921600, rate_hz=RATE).start()
        self.clock_t0 = self.pty.flock.origin  # the performance's time 0 on the flock's clock (SYSTEM)
        self.data = tempfile.mkdtemp(prefix="flockcal-bench-")
        extra = []
        if self.streams:
            if not PRINT_DEVICES.exists():
                raise SystemExit(f"bench_server: --streams needs VRPN's client at {PRINT_DEVICES}")
            self.vrpn_port = free_port()
            self.vmc = VmcDrain()
            self.attached.append(self.vmc)
            extra = ["--vrpn", str(self.vrpn_port), "--osc", f"127.0.0.1:{self.vmc.port}"]
        self.proc = ServerProcess(["--device", self.pty.device, "--birds", "16", "--fast-init", "--scale", "72",
                                   "--baud", "921600", "--data-dir", self.data, "--names", ",".join(performer.names),
                                   *extra],
                                  free_port(), log_path=os.path.join(self.data, "serve.log"), cwd=self.data)
        saved = os.environ.get("PYTHONPATH")
        try:
            check_imports(self.site, self.data)  # with the environment the child gets below
            # The child copies this process's environment when it starts.
            os.environ["PYTHONPATH"] = os.pathsep.join(x for x in (self.site, saved) if x)
            self.proc.start()
            wait_connected(self.proc.url, frames=int(RATE))
            httpx.post(self.proc.url + "/api/sessions", json={"performer": "bench"}).raise_for_status()
            if self.streams:  # VRPN's own client on its UDP channel, its printing thrown away
                client = subprocess.Popen([str(PRINT_DEVICES), f"flockcal@127.0.0.1:{self.vrpn_port}"],
                                          stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
                self.attached.append(client)
            time.sleep(3.0)  # let the fit settle into its steady state
        except BaseException:
            self.__exit__()
            raise
        finally:
            if saved is None:
                os.environ.pop("PYTHONPATH", None)
            else:
                os.environ["PYTHONPATH"] = saved
        self.url = self.proc.url.replace("http://", "ws://") + "/ws/live"
        return self

    def __exit__(self, *exc) -> None:
        try:
            for thing in self.attached:
                if isinstance(thing, subprocess.Popen):
                    thing.terminate()
                    thing.wait(10)
                else:
                    thing.close()
            self.proc.stop()
        finally:
            self.pty.stop()
            shutil.rmtree(self.data, ignore_errors=True)

    def tracker_cpu(self) -> float:
        """CPU seconds of the fake tracker's thread (in this process)."""
        with open(f"/proc/self/task/{self.pty._thread.native_id}/stat") as fh:
            fields = fh.read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


PRINT_DEVICES = Path(__file__).resolve().parents[1].parent / "shared" / "tools" / "vrpn" / "vrpn_print_devices"


class VmcDrain:
    """A VMC receiver that takes every datagram and throws it away (a thread of this process)."""

    def __init__(self):
        import socket
        import threading

        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.5)
        self.port = self.sock.getsockname()[1]
        self.received = 0
        self._stop = False
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self):
        while not self._stop:
            try:
                self.sock.recv(65536)
                self.received += 1
            except OSError:
                pass

    def close(self):
        self._stop = True
        self._thread.join(5)
        self.sock.close()


def measure_window(svc: Service, seconds: float, dashboards: int, probe_hz: float) -> dict:
    """One window's figures: latency at the probe, CPU of the service process and its threads, the
    fake tracker's thread, refits and slip alarms."""
    pid, url = svc.proc.proc.pid, svc.proc.url
    st0 = httpx.get(url + "/api/status").json()
    cpu0, wall0, threads0, trk0 = cpu_seconds(pid), time.monotonic(), thread_cpu(pid), svc.tracker_cpu()
    lat, probe_rate = measure_apart(svc.url, svc.clock_t0, seconds, dashboards, probe_hz)
    lat = np.array(lat) * 1000
    cpu1, wall1, threads1, trk1 = cpu_seconds(pid), time.monotonic(), thread_cpu(pid), svc.tracker_cpu()
    st1 = httpx.get(url + "/api/status").json()
    session = st1["session"]["id"]
    slips = [e for e in httpx.get(f"{url}/api/sessions/{session}/events").json()["events"] if e["type"] == "slip"]
    wall = wall1 - wall0
    p50, p99 = np.percentile(lat, [50, 99])
    return {
        "seconds": seconds, "dashboards": dashboards, "probe_rate": probe_rate,
        "cpu": 100 * (cpu1 - cpu0) / wall, "tracker_cpu": 100 * (trk1 - trk0) / wall,
        "threads": {k: 100 * (v - threads0.get(k, 0.0)) / wall for k, v in threads1.items()},
        "frames_hz": (st1["frames"] - st0["frames"]) / wall, "dropped": st1["dropped_records"] - st0["dropped_records"],
        "fits_hz": (st1["fits"] - st0["fits"]) / wall, "fit_ms": st1["fit_ms"], "slips": len(slips),
        "samples": len(lat), "p50": p50, "p99": p99, "max": lat.max(), "load": os.getloadavg()[0],
    }


def window(svc: Service, seconds: float, dashboards: int, probe_hz: float) -> None:
    """Measure and print one window: latency at the probe, CPU of the service process and its threads."""
    w = measure_window(svc, seconds, dashboards, probe_hz)
    print(f"flockcal serve, 16 birds at {RATE:g} Hz on a pty, {seconds:g} s, {dashboards} extra dashboards, "
          f"latency probe subscribed at {w['probe_rate']:g} Hz (in its own process)")
    print(f"  frames received     {w['frames_hz']:8.1f} /s   (dropped records in the window: {w['dropped']})")
    print(f"  full refits         {w['fits_hz']:8.1f} /s   (target >= 30; {w['fit_ms']} ms each)")
    print(f"  slip alarms         {w['slips']:8d}     (none expected: the performer's sensors stay put)")
    print(f"  latency samples     {w['samples']:8d}")
    print(f"  latency p50         {w['p50']:8.1f} ms")
    print(f"  latency p99         {w['p99']:8.1f} ms   (target < 50 ms: {50 / w['p99']:.2f}x margin)")
    print(f"  latency max         {w['max']:8.1f} ms")
    print(f"  service CPU         {w['cpu']:8.1f} % of one core   (target < 15 %: {15 / w['cpu']:.2f}x margin)")
    for name, share in sorted(w["threads"].items(), key=lambda kv: -kv[1]):
        if share >= 0.5:
            print(f"    thread {name:18s} {share:5.1f} %")
    print(f"  fake tracker thread {w['tracker_cpu']:8.1f} % of one core   (in the benchmark's process, not the service's)")
    print(f"  load average        {w['load']:8.2f}   (on {os.cpu_count()} cores; other work inflates the latency)")


def ab_order(rounds: int):
    """(round, side) in the order an A/B run takes them: AB, BA, AB, ... so each round's two runs neighbour
    each other and the first side alternates (what `round_ratios` pairs)."""
    for k in range(rounds):
        for side in ("AB" if k % 2 == 0 else "BA"):
            yield k, side


def ratio_line(what: str, ratios: list[float]) -> str:
    return f"{what} B/A per round: {' '.join(f'{x:.2f}' for x in ratios)}; median {np.median(ratios):.2f}"


def round_ratios(runs: list[tuple[str, dict]], key: str) -> list[float]:
    """B/A of `key` for each round: neighbouring runs (one A, one B, in the order they ran), so drift in
    the machine's load moves both sides of a ratio."""
    ratios = []
    for k in range(0, len(runs) - 1, 2):
        (s0, w0), (_, w1) = runs[k], runs[k + 1]
        a, b = (w0, w1) if s0 == "A" else (w1, w0)
        ratios.append(b[key] / a[key] if a[key] else float("nan"))
    return ratios


def check_imports(site: str, cwd: str) -> None:
    """Stop unless a child started like the service (this environment, from `cwd`) imports the service's
    and the solver's code from `site` (symlinks resolved to where they point)."""
    probe = "import flockcal.server, flockcal.solver; print(flockcal.server.__file__); print(flockcal.solver.__file__)"
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(x for x in (site, os.environ.get("PYTHONPATH")) if x))
    out = subprocess.run([sys.executable, "-c", probe], cwd=cwd, env=env, capture_output=True, text=True, check=False)
    want = {str(Path(site, "flockcal", part, "__init__.py").resolve()) for part in ("server", "solver")}
    got = {str(Path(line).resolve()) for line in out.stdout.split()}
    if out.returncode != 0 or got != want:
        raise SystemExit(f"bench_server: the service would not run the code asked for: it imports {sorted(got)} "
                         f"(wanted {sorted(want)}){' — ' + out.stderr.strip()[-500:] if out.returncode else ''}")


def tree_site(into: str) -> str:
    """This working tree as an importable `flockcal` package under `into` (symlinks into it), as
    `export_revision` lays out a revision: B runs what is here, whatever the editable install points at."""
    return _site(Path(__file__).resolve().parents[1], Path(into))


def _site(src: Path, into: Path) -> str:
    # pyproject's package-dir: flockcal.<part> lives in the top-level folder <part>.
    pkg = into / "site" / "flockcal"
    pkg.mkdir(parents=True)
    for entry in (src / "flockcal").iterdir():
        (pkg / entry.name).symlink_to(entry)
    for part in ("drivers", "simulator", "solver", "server"):
        (pkg / part).symlink_to(src / part)
    return str(into / "site")


def export_revision(rev: str, into: str) -> str:
    """REV's tree as an importable `flockcal` package under `into`; returns the folder for PYTHONPATH."""
    repo = Path(__file__).resolve().parents[1]
    src = Path(into, "src")
    src.mkdir(parents=True)
    archive = subprocess.run(["git", "-C", str(repo), "archive", rev], capture_output=True, check=False)
    if archive.returncode != 0:
        raise SystemExit(f"bench_server: git archive {rev}: {archive.stderr.decode().strip()}")
    subprocess.run(["tar", "-x", "-C", str(src)], input=archive.stdout, check=True)
    return _site(src, Path(into))


def ab(rev: str, rounds: int, seconds: float, dashboards: int, probe_hz: float) -> int:
    repo = Path(__file__).resolve().parents[1]
    commit = subprocess.run(["git", "-C", str(repo), "rev-parse", "--short", rev], capture_output=True, text=True)
    if commit.returncode != 0:
        print(f"bench_server: no git revision {rev!r} in {repo}", file=sys.stderr)
        return 2
    head = subprocess.run(["git", "-C", str(repo), "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    dirty = subprocess.run(["git", "-C", str(repo), "status", "--porcelain", "--untracked-files=no"],
                           capture_output=True, text=True).stdout.strip()
    tmp = tempfile.mkdtemp(prefix="flockcal-ab-")
    try:
        sides = {"A": export_revision(rev, os.path.join(tmp, "a")), "B": tree_site(os.path.join(tmp, "b"))}
        label = {"A": f"{rev} ({commit.stdout.strip()})", "B": f"this tree ({head}{' + changes' if dirty else ''})"}
        print(f"A/B: A = {label['A']}, B = {label['B']}; 16 birds at {RATE:g} Hz, {seconds:g} s windows, "
              f"probe at {probe_hz:g} Hz, {dashboards} extra dashboards, {rounds} rounds")
        runs: list[tuple[str, dict]] = []
        for r, side in ab_order(rounds):
            with Service(sides[side]) as svc:
                w = measure_window(svc, seconds, dashboards, probe_hz)
            runs.append((side, w))
            top = ", ".join(f"{k} {v:.1f}" for k, v in sorted(w["threads"].items(), key=lambda kv: -kv[1]) if v >= 0.5)
            print(f"  round {r + 1} {side}: service {w['cpu']:5.1f} % ({top}); tracker {w['tracker_cpu']:5.1f} %; "
                  f"p99 {w['p99']:5.1f} ms; refits {w['fits_hz']:4.1f}/s ({w['fit_ms']} ms); slip alarms {w['slips']}; "
                  f"load {w['load']:.1f}", flush=True)
        print("medians (A, B):")
        for key, what in (("cpu", "service CPU % of one core"), ("tracker_cpu", "fake tracker CPU %"),
                          ("p99", "latency p99 ms"), ("fits_hz", "refits /s"), ("slips", "slip alarms")):
            a = np.median([w[key] for s, w in runs if s == "A"])
            b = np.median([w[key] for s, w in runs if s == "B"])
            print(f"  {what:27s} A {a:6.1f}   B {b:6.1f}")
        print("  " + ratio_line("service CPU", round_ratios(runs, "cpu")))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return 0


def code_site(rev: str | None, into: str) -> tuple[str, str]:
    """(site, label) of the code a streams run serves: git revision `rev`, or this tree when None."""
    if rev is None:
        return tree_site(into), "this tree"
    commit = subprocess.run(["git", "-C", str(Path(__file__).resolve().parents[1]), "rev-parse", "--short", rev],
                            capture_output=True, text=True)
    if commit.returncode != 0:
        raise SystemExit(f"bench_server: no git revision {rev!r}")
    return export_revision(rev, into), f"{rev} ({commit.stdout.strip()})"


def streams_ab(rounds: int, seconds: float, dashboards: int, probe_hz: float, rev: str | None = None) -> int:
    """The service without (A) and with (B) the VRPN and VMC streams and their clients, in turn."""
    tmp = tempfile.mkdtemp(prefix="flockcal-streams-ab-")
    try:
        site, code = code_site(rev, tmp)
        print(f"streams A/B of {code}: A = no streams; B = --vrpn and --osc, vrpn_print_devices and "
              f"a VMC receiver attached; 16 birds at {RATE:g} Hz, {seconds:g} s windows, probe at {probe_hz:g} Hz, "
              f"{dashboards} extra dashboards, {rounds} rounds")
        runs: list[tuple[str, dict]] = []
        for r, side in ab_order(rounds):
            with Service(site, streams=side == "B") as svc:
                w = measure_window(svc, seconds, dashboards, probe_hz)
                if side == "B":
                    st = httpx.get(svc.proc.url + "/api/status").json()["outputs"]
                    w["clients"] = len(st["vrpn"]["clients"])
                    w["vmc_received"] = svc.vmc.received
            runs.append((side, w))
            top = ", ".join(f"{k} {v:.1f}" for k, v in sorted(w["threads"].items(), key=lambda kv: -kv[1]) if v >= 0.5)
            extra = f"; VRPN clients {w['clients']}, VMC bundles received {w['vmc_received']}" if side == "B" else ""
            print(f"  round {r + 1} {side}: service {w['cpu']:5.1f} % ({top}); p99 {w['p99']:5.1f} ms; "
                  f"refits {w['fits_hz']:4.1f}/s; load {w['load']:.1f}{extra}", flush=True)
        diffs = []
        for k in range(0, len(runs) - 1, 2):
            (s0, w0), (_, w1) = runs[k], runs[k + 1]
            a, b = (w0, w1) if s0 == "A" else (w1, w0)
            diffs.append(b["cpu"] - a["cpu"])
        own = [w["threads"].get("fc-outputs", 0.0) for s, w in runs if s == "B"]
        print(f"  streams add (B - A, points of one core) per round: {' '.join(f'{d:+.1f}' for d in diffs)}; "
              f"median {np.median(diffs):+.1f} (target at most +3)")
        print(f"  their thread fc-outputs: {' '.join(f'{x:.1f}' for x in own)} % of one core; median {np.median(own):.1f}")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return 0


def _paired_side(site: str, streams: bool, conn) -> None:
    """One side of a paired run, in a process of its own with its fake tracker: serve until told to stop."""
    try:
        with Service(site, streams=streams) as svc:
            if streams:  # the streams' cost is what they cost sending bones: the session's fit must be a humanoid
                wait_streaming(svc.proc.url)
            conn.send((svc.proc.proc.pid, svc.proc.url))
            conn.recv()
            conn.send(svc.vmc.received if streams else None)
    except BaseException as exc:
        conn.send(exc)
        raise


def wait_streaming(url: str, timeout: float = 120.0) -> None:
    """Until the service's streams send the humanoid's bones to a connected VRPN client: a live session's first
    fits (the first 10-20 s of the routine) are not human-shaped yet, and bones cost what sending none does not."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        out = httpx.get(url + "/api/status").json()["outputs"]
        if out["humanoid"]["streaming"] and any(c["state"] == "connected" for c in out["vrpn"]["clients"]):
            return
        time.sleep(0.5)
    raise RuntimeError(f"the streams sent no bones within {timeout:g} s: {out['humanoid']}")


def _paired_reading(pid: int, url: str) -> tuple:
    return cpu_seconds(pid), thread_cpu(pid), httpx.get(url + "/api/status").json()["fits"], time.monotonic()


def streams_paired(rounds: int, windows: int, seconds: float, rev: str | None = None) -> int:
    """The service without (A) and with (B) the streams at the same time; each window's B − A in points."""
    tmp = tempfile.mkdtemp(prefix="flockcal-streams-paired-")
    ctx = multiprocessing.get_context("spawn")
    diffs: list[list[float]] = []
    nofit: list[float] = []
    per_thread: dict[str, list[float]] = {}
    own: list[float] = []
    sides_cpu: dict[str, list[float]] = {"A": [], "B": []}
    fits: dict[str, list[float]] = {"A": [], "B": []}
    try:
        site, code = code_site(rev, tmp)
        print(f"streams paired A/B of {code}: A (no streams) and B (--vrpn and --osc, vrpn_print_devices and a VMC "
              f"receiver attached) at the same time, each with its fake tracker in a process of its own; 16 birds "
              f"at {RATE:g} Hz, no websocket client; {rounds} rounds of {windows} windows of {seconds:g} s", flush=True)
        for r in range(rounds):
            procs, conns, where = {}, {}, {}
            try:
                for side in ("AB" if r % 2 == 0 else "BA"):
                    here, there = ctx.Pipe()
                    procs[side] = ctx.Process(target=_paired_side, args=(site, side == "B", there), daemon=True)
                    procs[side].start()
                    conns[side] = here
                for side, conn in conns.items():
                    got = conn.recv()
                    if isinstance(got, BaseException):
                        raise SystemExit(f"bench_server: side {side} did not start: {got}")
                    where[side] = got
                round_diffs = []
                for _ in range(windows):
                    before = {s: _paired_reading(*where[s]) for s in "AB"}
                    time.sleep(seconds)
                    after = {s: _paired_reading(*where[s]) for s in "AB"}
                    share = {}
                    for s in "AB":
                        (c0, th0, f0, w0), (c1, th1, f1, w1) = before[s], after[s]
                        wall = w1 - w0
                        th = {k: 100 * (v - th0.get(k, 0.0)) / wall for k, v in th1.items()}
                        share[s] = (100 * (c1 - c0) / wall, th)
                        sides_cpu[s].append(share[s][0])
                        fits[s].append((f1 - f0) / wall)
                    (ca, tha), (cb, thb) = share["A"], share["B"]
                    round_diffs.append(cb - ca)
                    nofit.append((cb - thb.get("fc-fit", 0.0)) - (ca - tha.get("fc-fit", 0.0)))
                    for k in set(tha) | set(thb):
                        per_thread.setdefault(k, []).append(thb.get(k, 0.0) - tha.get(k, 0.0))
                    own.append(thb.get("fc-outputs", 0.0))
                diffs.append(round_diffs)
                print(f"  round {r + 1}: B - A per window {' '.join(f'{d:+.1f}' for d in round_diffs)}; median "
                      f"{np.median(round_diffs):+.1f}; A {np.median(sides_cpu['A'][-windows:]):.1f} %, "
                      f"B {np.median(sides_cpu['B'][-windows:]):.1f} %; refits A {np.median(fits['A'][-windows:]):.1f}/s, "
                      f"B {np.median(fits['B'][-windows:]):.1f}/s; load {os.getloadavg()[0]:.1f}", flush=True)
            finally:
                for side, conn in conns.items():
                    try:
                        conn.send("stop")
                    except OSError:
                        pass
                for p in procs.values():
                    p.join(60)
                    if p.is_alive():
                        p.terminate()
                        p.join(10)
        every = [d for rd in diffs for d in rd]
        q1, q3 = np.percentile(every, [25, 75])
        print(f"  streams add (B - A, points of one core): median {np.median(every):+.1f} over {len(every)} windows "
              f"(quartiles {q1:+.1f} {q3:+.1f}; round medians {' '.join(f'{np.median(rd):+.1f}' for rd in diffs)}; "
              f"target at most +3)")
        print(f"  without the fit thread (its CPU follows the refit rate each side got): median {np.median(nofit):+.1f}")
        tops = sorted(per_thread.items(), key=lambda kv: -abs(np.median(kv[1])))
        print("  per thread, median B - A: " + ", ".join(f"{k} {np.median(v):+.1f}" for k, v in tops
                                                        if abs(np.median(v)) >= 0.1))
        print(f"  their thread fc-outputs: median {np.median(own):.1f} % of one core (range {min(own):.1f}-{max(own):.1f})")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
