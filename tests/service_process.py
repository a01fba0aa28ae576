"""`flockcal serve` as a child process the way an operator or a unit starts it, for the tests of what happens
when things run out or break: its own output in a file, optional resource limits, reaped whatever happens.
"""

from __future__ import annotations

import os
import resource
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx


class Serve:
    """`python -m flockcal serve ARGS` on a free port; `nofile=(soft, hard)` sets its open-files limits
    first (what a systemd unit's LimitNOFILE, or the lack of one, gives it); `prefix` runs it through a
    command that execs it (`unshare ... sh -c '...; exec "$@"'`). Use as a context manager: the child is
    stopped (SIGINT, then SIGKILL after 20 s) and reaped on the way out."""

    def __init__(self, args: list[str], port: int, log: Path, nofile: tuple[int, int] | None = None,
                 prefix: list | None = None):
        self.port = port
        self.url = f"http://127.0.0.1:{port}"
        args = [str(a) for a in args]
        if "--data-dir" not in args:  # never the user's own data directory (one service per directory)
            args += ["--data-dir", str(Path(log).parent / f"data-{port}")]
        self.args = [*map(str, prefix or []), sys.executable, "-m", "flockcal", "serve", "--http-port", str(port),
                     *args]
        self.log = Path(log)
        self.nofile = nofile
        self.proc: subprocess.Popen | None = None

    def _limits(self) -> None:
        if self.nofile is not None:
            resource.setrlimit(resource.RLIMIT_NOFILE, self.nofile)

    def start(self, ready_s: float = 60.0) -> "Serve":
        env = dict(os.environ, FLOCKCAL_FAST_INIT="1")
        with open(self.log, "ab") as out:
            self.proc = subprocess.Popen(self.args, stdout=out, stderr=subprocess.STDOUT, env=env,
                                         preexec_fn=self._limits)

        def ready() -> bool:
            if self.proc.poll() is not None:
                raise RuntimeError(f"serve exited with {self.proc.returncode}: {self.output()[-2000:]}")
            try:
                return httpx.get(self.url + "/api/status", timeout=2).status_code == 200
            except httpx.HTTPError:
                return False

        wait_for(ready, ready_s, lambda: f"serve ready ({self.output()[-2000:]})")
        return self

    def output(self) -> str:
        return self.log.read_text(errors="replace") if self.log.exists() else ""

    def stop(self, sig: int = signal.SIGINT, timeout: float = 30.0) -> int:
        """Send `sig` and reap the child; its exit code (SIGKILL after `timeout`, which fails the caller)."""
        if self.proc is None:
            return 0
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)
                raise
        return self.proc.returncode

    def __enter__(self) -> "Serve":
        return self.start()

    def __exit__(self, *exc) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
        if self.proc is not None:
            self.proc.wait(10)


def wait_for(condition, timeout: float, what, every: float = 0.05):
    """Poll `condition()` until it returns something true; its value. AssertionError naming `what` (a string,
    or a function giving one) after `timeout` seconds. The one place the tests wait on real time: `timeout`
    only ends a hung test (every caller waits on a condition), `every` is how often it is looked at."""
    deadline = time.monotonic() + timeout
    while True:
        value = condition()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"{what() if callable(what) else what}: not within {timeout:g} s")
        time.sleep(every)


def run_serve(args: list[str], timeout: float = 60.0) -> subprocess.CompletedProcess:
    """`flockcal serve ARGS` expected to exit by itself (a refused start)."""
    return subprocess.run([sys.executable, "-m", "flockcal", "serve", "--http-port", "0", *map(str, args)],
                          capture_output=True, text=True, timeout=timeout, env=dict(os.environ, FLOCKCAL_FAST_INIT="1"))
