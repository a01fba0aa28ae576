"""Probes the service-breaking tests share (tests/test_server_breaks.py, test_server_stalled_downloads.py,
test_server_damaged_files.py): a six-sensor simulated performer, this process's descriptor limit, whether the
service closed a socket, and a status request with a deadline.
"""

from __future__ import annotations

import resource
import socket

import httpx
import pytest


def sim6(name: str) -> list[str]:
    """A simulated performer with the six sensors of the golden skeleton file."""
    return ["--device", f"sim://{name}?birds=6&motion=exercise&rate=100", "--birds", "6"]


def own_open_files(n: int) -> None:
    """Let this test process hold `n` descriptors (the attacker's sockets), or skip."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft >= n:
        return
    if hard != resource.RLIM_INFINITY and hard < n:
        pytest.skip(f"the test needs {n} open files; this machine's hard limit is {hard}")
    resource.setrlimit(resource.RLIMIT_NOFILE, (n, hard))


def closed_by_peer(sock: socket.socket) -> bool:
    """True once the service has closed (or reset) this connection; reads what is waiting, never blocks."""
    sock.setblocking(False)
    while True:
        try:
            if sock.recv(65536) == b"":
                return True
        except BlockingIOError:
            return False
        except OSError:
            return True


def status_within(url: str, seconds: float = 5.0) -> httpx.Response:
    return httpx.get(url + "/api/status", timeout=seconds)
