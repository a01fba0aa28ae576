"""Figures of docs/service.md "When things break": what a flood of half-sent requests does to `flockcal serve`,
and what checking the database at start costs.

    python benchmarks/bench_breaks.py attack [--connections 1100] [--soft 1024] [--seconds 45]
    python benchmarks/bench_breaks.py quick-check [--mb 200]

`attack` starts serve (built-in simulator) with the given soft open-files limit (what a systemd unit without
LimitNOFILE gets), opens the connections, sends each half a request, and probes /api/status every 0.5 s (5 s
timeout) for `--seconds`; prints the answers, the slowest probe and how much the service's output grew.
`quick-check` builds a database of residual rows of about `--mb` MB and times `PRAGMA quick_check` on it (the
service runs it at every start). Prints figures; asserts nothing.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import socket
import sqlite3
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def attack(connections: int, soft: int, seconds: float) -> None:
    hard = resource.getrlimit(resource.RLIMIT_NOFILE)[1]
    resource.setrlimit(resource.RLIMIT_NOFILE, (min(hard, connections + 500), hard))
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    with tempfile.TemporaryDirectory() as tmp:
        log = Path(tmp) / "serve.log"
        with open(log, "wb") as out:
            proc = subprocess.Popen([sys.executable, "-m", "flockcal", "serve", "--http-port", str(port), "--data-dir",
                                     str(Path(tmp) / "data")], stdout=out, stderr=subprocess.STDOUT,
                                    env=dict(os.environ, FLOCKCAL_FAST_INIT="1"),
                                    preexec_fn=lambda: resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard)))
        socks = []
        try:
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline:
                try:
                    if httpx.get(url + "/api/status", timeout=2).status_code == 200:
                        break
                except httpx.HTTPError:
                    time.sleep(0.1)
            before = log.stat().st_size
            start = time.monotonic()
            for _ in range(connections):
                s = socket.socket()
                s.setblocking(False)
                try:
                    s.connect(("127.0.0.1", port))
                except BlockingIOError:
                    pass
                socks.append(s)
            time.sleep(0.5)
            for s in socks:
                try:
                    s.send(b"GET /api/status HTTP/1.1\r\nHost: 127.0.0.1\r\n")
                except OSError:
                    pass
            answers, slowest = {}, 0.0
            while time.monotonic() - start < seconds:
                t = time.monotonic()
                try:
                    code = httpx.get(url + "/api/status", timeout=5).status_code
                except httpx.HTTPError as exc:
                    code = type(exc).__name__
                slowest = max(slowest, time.monotonic() - t)
                answers[code] = answers.get(code, 0) + 1
                time.sleep(0.5)
            try:
                counts = httpx.get(url + "/api/status", timeout=5).json().get("connections")
            except (httpx.HTTPError, ValueError):
                counts = None
            print(f"{connections} half-sent requests, soft limit {soft} (hard {hard}), {seconds:g} s: /api/status "
                  f"answers {answers}, slowest probe {slowest:.2f} s; output +{log.stat().st_size - before} bytes; "
                  f"connections {json.dumps(counts)}")
        finally:
            for s in socks:
                s.close()
            proc.send_signal(2)
            try:
                proc.wait(30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(10)


def quick_check(mb: float) -> None:
    from flockcal.server.store import Store

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "flockcal.sqlite3"
        store = Store(path)
        row = json.dumps({f"joint{k}": 1.2345678 for k in range(15)})
        batch = [(t * 0.05, json.loads(row)) for t in range(20_000)]
        while path.stat().st_size + Path(str(path) + "-wal").stat().st_size < mb * 1e6:
            store.add_residuals("20260101-000000-aaaaaa", batch)
        store.close()
        with sqlite3.connect(path) as db:
            db.execute("PRAGMA wal_checkpoint(TRUNCATE)")
        size = path.stat().st_size
        t = time.perf_counter()
        Store(path).close()
        opened = time.perf_counter() - t
        print(f"database of {size / 1e6:.0f} MB: opened and checked (PRAGMA quick_check) in {opened:.2f} s")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="what", required=True)
    a = sub.add_parser("attack")
    a.add_argument("--connections", type=int, default=1100)
    a.add_argument("--soft", type=int, default=1024)
    a.add_argument("--seconds", type=float, default=45.0)
    q = sub.add_parser("quick-check")
    q.add_argument("--mb", type=float, default=200.0)
    args = p.parse_args()
    if args.what == "attack":
        attack(args.connections, args.soft, args.seconds)
    else:
        quick_check(args.mb)


if __name__ == "__main__":
    main()
