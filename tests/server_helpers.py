"""Run the real service for tests and benchmarks: uvicorn on a free loopback port, in a thread or a
child process (for restarts and kill -9), plus the fake tracker on a pty as its device.
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import threading
from pathlib import Path

import httpx
import numpy as np

from service_process import wait_for


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_ready(url: str, timeout: float = 30.0, token: str | None = None, proc=None) -> None:
    headers = {"Authorization": f"Bearer {token}"} if token else {}
    last = [None]

    def ready() -> bool:
        if proc is not None and proc.poll() is not None:
            raise RuntimeError(f"the service exited with code {proc.returncode} before it was ready")
        try:
            r = httpx.get(url + "/api/status", headers=headers, timeout=2)
        except httpx.HTTPError as exc:
            last[0] = exc
            return False
        last[0] = r.text
        return r.status_code == 200

    wait_for(ready, timeout, lambda: f"the service at {url} ready (last answer: {last[0]})")


def wait_connected(url: str, timeout: float = 30.0, token: str | None = None, frames: int = 1) -> dict:
    """Poll /api/status until the tracker streams (at least `frames` frames received)."""
    headers = {"Authorization": f"Bearer {token}"} if token else {}

    def streaming():
        st = httpx.get(url + "/api/status", headers=headers, timeout=5).json()
        return st if st.get("connected") and st.get("frames", 0) >= frames else None

    return wait_for(streaming, timeout, f"the tracker streams {frames} frame(s)")


def run_clock(clock, seconds: float, dt: float = 0.05, until=None, timeout: float = 60.0) -> float:
    """Let `seconds` of a `ManualClock` pass (with `until`, only until it holds) in steps of `dt`, each once
    every thread that follows the clock has caught up with the last (`ManualClock.idle`): the fake tracker,
    the reader and the service move as time passing moves them, however slowly a loaded machine runs them.
    Returns the seconds that passed; AssertionError when `until` did not hold within `seconds`."""
    start, steps = clock.monotonic(), max(1, round(seconds / dt))
    for k in range(1, steps + 1):
        if until is not None and until():
            return (k - 1) * seconds / steps
        # To start + k steps exactly: a thread that sleeps `seconds` from `start` wakes at the last.
        clock.advance_to(start + seconds if k == steps else start + k * seconds / steps)
        wait_for(clock.idle, timeout, "the threads that follow the clock catch up", every=0.001)
    assert until is None or until(), f"not within {seconds:g} s of the clock"
    return seconds


@contextlib.contextmanager
def manual_service(settings, wall: float = 1.7e9):
    """The whole service on a `ManualClock` the test moves (`run_clock`): the simulated tracker (a sim://
    device is made on the service's clock), the reader, the pipeline, leases, retention and stamps, under
    uvicorn on a thread. Yields (ServerThread, clock) once the tracker has sent 10 frames."""
    from flockcal.clock import ManualClock
    from flockcal.server.service import Service

    clock = ManualClock(wall=wall, monotonic=1000.0)
    service = Service(settings, clock=clock)
    with ServerThread(settings, service) as srv:
        run_clock(clock, 30.0, until=lambda: service.source.status().frames >= 10)
        yield srv, clock


def status(url: str, token: str | None = None) -> dict:
    """GET /api/status."""
    headers = {"Authorization": f"Bearer {token}"} if token else {}
    return httpx.get(url + "/api/status", headers=headers, timeout=10).json()


def start_session(url: str, performer: str = "Ann", **body) -> str:
    """POST /api/sessions as the dashboard does; the new session's id (a refusal fails the test)."""
    r = httpx.post(url + "/api/sessions", json={"performer": performer, **body}, timeout=30)
    assert r.status_code == 201, r.text
    return r.json()["id"]


class GuestSource:
    """A simulated performer as the pose source of a fake tracker, whose routine starts over at `begin()`
    (a kiosk guest starts moving when their session starts); `begin(other, lead_s)` swaps in the next
    guest, who must wear the same sensors. Pass it as the tracker's source: `tracker.flock.source = …`.

    A new guest has another body: frames of the last one in a session would mix two skeletons. So swap
    with a lead (`lead_s` ≈ 0.3 s: the tracker computes poses up to 0.1 s ahead, and frames in flight),
    wait that long, then start the session; the routine's clock starts at the end of the lead.
    `clock`: the tracker's time (`tracker.flock.time`).
    """

    def __init__(self, performer, clock):
        self.names, self.n_sensors = performer.names, performer.n_sensors
        self.full_scale_in = performer.full_scale_in
        self.clock = clock
        self._now = (performer, 0.0)  # swapped whole: the tracker's thread reads it

    @property
    def performer(self):
        return self._now[0]

    def begin(self, performer=None, lead_s: float = 0.0) -> None:
        performer = self._now[0] if performer is None else performer
        if tuple(performer.names) != tuple(self.names):
            raise ValueError(f"the next guest wears {list(performer.names)}, not the tracker's {list(self.names)}")
        self._now = (performer, float(self.clock()) + float(lead_s))

    def poses(self, times):
        performer, start = self._now
        return performer.poses(np.asarray(times, dtype=float) - start)


class ServerThread:
    """The app under uvicorn on a background thread of this process."""

    def __init__(self, settings, service=None):
        import uvicorn

        from flockcal.server.app import create_app

        self.settings = settings
        self.app = create_app(settings, service)
        config = uvicorn.Config(self.app, host=settings.host, port=settings.http_port, log_level="warning",
                                lifespan="on", ws_per_message_deflate=False)
        self.server = uvicorn.Server(config)
        self.thread = threading.Thread(target=self.server.run, name="uvicorn", daemon=True)
        self.url = f"http://127.0.0.1:{settings.http_port}"

    @property
    def service(self):
        return self.app.state.service

    def start(self, timeout: float = 30.0) -> "ServerThread":
        from flockcal.server.listen import listen_socket

        sock = listen_socket(self.settings.host, self.settings.http_port, self.settings.send_buffer_bytes)
        self.thread = threading.Thread(target=self.server.run, kwargs={"sockets": [sock]}, name="uvicorn", daemon=True)
        self.thread.start()

        def started() -> bool:
            if not self.thread.is_alive():
                raise RuntimeError("uvicorn did not start")
            return self.server.started

        wait_for(started, timeout, "uvicorn started", every=0.02)
        return self

    def stop(self) -> None:
        self.server.should_exit = True
        self.thread.join(20)

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()


class ServerProcess:
    """`python -m flockcal serve …` as a child process (so it can be restarted or killed with -9)."""

    def __init__(self, args: list[str], port: int, log_path: str | Path | None = None,
                 cwd: str | Path | None = None):
        self.port = port
        self.cwd = cwd  # `-m` puts the child's working folder first on its import path
        self.url = f"http://127.0.0.1:{port}"
        self.args = [sys.executable, "-m", "flockcal", "serve", "--http-port", str(port), *args]
        self.log_path = log_path
        self.proc: subprocess.Popen | None = None

    def start(self, timeout: float = 60.0, token: str | None = None) -> "ServerProcess":
        out = open(self.log_path, "ab") if self.log_path else subprocess.DEVNULL
        env = dict(os.environ, FLOCKCAL_FAST_INIT="1")
        try:
            self.proc = subprocess.Popen(self.args, stdout=out, stderr=subprocess.STDOUT, env=env, cwd=self.cwd)
        finally:
            if out is not subprocess.DEVNULL:
                out.close()  # the child has its own copy
        try:
            wait_ready(self.url, timeout, token, self.proc)
        except BaseException:
            self.stop()  # never leave a service behind that did not come up in time
            raise
        return self

    def kill9(self) -> None:
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(10)

    def stop(self) -> None:
        if self.proc and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(20)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)


class SlowDownload:
    """A GET whose client reads the status line and headers and then nothing more until `body()`, with a
    small receive buffer (64 KB): the rest of a large body stays with the server, the download in progress.
    (A plain client's buffer grows with the kernel's autotuning, up to 32 MB on the CI machines: the server
    would finish sending a whole take at once.)"""

    def __init__(self, base_url: str, path: str, headers: dict | None = None, rcvbuf: int = 65536):
        import socket

        url = httpx.URL(base_url)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
        self.sock.settimeout(30)
        self.sock.connect((url.host, url.port))
        extra = "".join(f"{k}: {v}\r\n" for k, v in (headers or {}).items())
        self.sock.sendall(f"GET {path} HTTP/1.1\r\nHost: {url.host}\r\n{extra}\r\n".encode())
        self._buf = b""
        while b"\r\n\r\n" not in self._buf:
            part = self.sock.recv(4096)
            assert part, "the server closed the connection before the response's head"
            self._buf += part
        head, self._buf = self._buf.split(b"\r\n\r\n", 1)
        lines = head.decode("latin-1").split("\r\n")
        self.status = int(lines[0].split(" ", 2)[1])
        self.headers = {k.strip().lower(): v.strip() for k, v in (ln.split(":", 1) for ln in lines[1:])}

    def _read(self, n: int) -> bytes:
        while len(self._buf) < n:
            part = self.sock.recv(1 << 20)
            if not part:
                raise AssertionError(f"the body was cut off: the connection closed {n - len(self._buf)} bytes short")
            self._buf += part
        out, self._buf = self._buf[:n], self._buf[n:]
        return out

    def _line(self) -> bytes:
        while b"\r\n" not in self._buf:
            part = self.sock.recv(1 << 20)
            if not part:
                raise AssertionError("the body was cut off inside a chunk header (a chunked body without its end)")
            self._buf += part
        line, self._buf = self._buf.split(b"\r\n", 1)
        return line

    def body(self) -> bytes:
        """The whole body (by Content-Length, or chunked to its last chunk); AssertionError when it is cut off."""
        try:
            if "content-length" in self.headers:
                return self._read(int(self.headers["content-length"]))
            assert self.headers.get("transfer-encoding") == "chunked", self.headers
            parts = []
            while (size := int(self._line().split(b";")[0], 16)) > 0:
                parts.append(self._read(size))
                assert self._read(2) == b"\r\n"
            return b"".join(parts)
        finally:
            self.sock.close()

    def close(self) -> None:
        self.sock.close()


@contextlib.contextmanager
def live_pipeline(tmp_path: Path, names: tuple[str, ...], rate_hz: float, **log_options):
    """The service's own Pipeline (no reader, no HTTP) with one live stage-profile session "s" begun, its frame
    log at tmp_path/s.frames (`log_options` go to FrameLog, e.g. flush_s) and its row in a real SQLite file;
    yields the pipeline, stopped on the way out. For tests that feed it frames the reader would hand over."""
    import time

    from flockcal.drivers.tracker_status import TrackerStatus
    from flockcal.server.framelog import FrameLog
    from flockcal.server.limits import DiskStatus
    from flockcal.server.live_session import LiveSession
    from flockcal.server.pipeline import Pipeline
    from flockcal.server.snapshot import SourceStatus
    from flockcal.server.store import Store
    from flockcal.solver.progress import profile

    store = Store(tmp_path / "flockcal.sqlite3")
    pipe = Pipeline(names, store, lambda: SourceStatus(TrackerStatus(connected=True), "test", False,
                                                         DiskStatus(False, None, 0)))
    pipe.start()
    try:
        store.insert_session({"id": "s", "performer": "p", "state": "live", "root": None, "hierarchy": None,
                              "names": list(names), "device": "test", "rate_hz": rate_hz, "created_at": time.time(),
                              "frames": 0, "recording": "s.frames", "profile": "stage"})
        prof = profile("stage", 0.005, 0.005 / 2 ** 0.5)
        log = FrameLog(tmp_path / "s.frames", list(names), rate_hz, **log_options)
        pipe.begin_session(LiveSession("s", "p", names, None, None, log, prof,
                                       started_wall=time.time(), started_mono=time.monotonic()))
        yield pipe
    finally:
        pipe.stop()
        if pipe.live is not None:  # a session left live: its log's writer thread goes with the log
            pipe.live.framelog.close()
