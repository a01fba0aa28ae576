"""Promises of docs/service.md that no other test held: one service per data directory (a second
`flockcal serve` on it is refused, naming the first one's pid) and the request body limit of exactly
64 KiB, with and without a Content-Length."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import httpx

from flockcal.server.settings import Settings
from server_helpers import ServerThread, free_port, wait_connected

LIMIT = 65_536  # docs/service.md: "request bodies are limited to 64 KiB (65,536 bytes)"


def test_a_second_service_on_the_same_data_directory_is_refused_and_the_first_keeps_running(tmp_path):
    # Tried: a second `flockcal serve` (a real process, as a second operator would start it) on the data
    # directory a running service writes.
    data = tmp_path / "data"
    settings = Settings(device="sim://one?birds=3&model=linkage&motion=exercise", birds=3, http_port=free_port(), data_dir=data)
    with ServerThread(settings) as srv:
        wait_connected(srv.url)
        second = subprocess.run(
            [sys.executable, "-m", "flockcal", "serve", "--device", "sim://two?birds=3&model=linkage", "--birds", "3",
             "--data-dir", str(data), "--http-port", str(free_port())],
            capture_output=True, text=True, timeout=120,
        )  # fmt: skip
        assert second.returncode == 2, second.stderr
        err = second.stderr.strip().splitlines()
        assert any(f"pid {os.getpid()}" in line and str(data) in line for line in err), second.stderr
        assert "Traceback" not in second.stderr
        # The first service was not disturbed: it still answers and can start a session.
        assert httpx.post(srv.url + "/api/sessions", json={"performer": "Ann"}).status_code == 201


def _body(size: int) -> bytes:
    """A valid session request padded with JSON whitespace to exactly `size` bytes."""
    core = json.dumps({"performer": "Bea"}).encode()
    return core[:-1] + b" " * (size - len(core)) + b"}"


def test_the_body_limit_is_exactly_64_kib_with_or_without_a_content_length(tmp_path):
    settings = Settings(device="sim://lim?birds=3&model=linkage&motion=exercise", birds=3, http_port=free_port(),
                        data_dir=tmp_path / "data")  # fmt: skip
    headers = {"Content-Type": "application/json"}
    with ServerThread(settings) as srv:
        wait_connected(srv.url)
        # Tried: one byte over the limit, declared in Content-Length.
        r = httpx.post(srv.url + "/api/sessions", content=_body(LIMIT + 1), headers=headers)
        assert r.status_code == 413 and str(LIMIT) in r.json()["detail"]
        # Tried: one byte over, sent chunked (no Content-Length to trust).
        def chunks(body=_body(LIMIT + 1)):
            for i in range(0, len(body), 4096):
                yield body[i : i + 4096]

        r = httpx.post(srv.url + "/api/sessions", content=chunks(), headers=headers)
        assert r.status_code == 413 and str(LIMIT) in r.json()["detail"]
        # Exactly at the limit, both ways: accepted (the session starts, and is stopped again).
        r = httpx.post(srv.url + "/api/sessions", content=_body(LIMIT), headers=headers)
        assert r.status_code == 201, r.text
        assert httpx.post(srv.url + f"/api/sessions/{r.json()['id']}/stop", timeout=60).status_code == 200
        body = _body(LIMIT)
        r = httpx.post(srv.url + "/api/sessions", content=(body[i : i + 4096] for i in range(0, LIMIT, 4096)), headers=headers)
        assert r.status_code == 201, r.text
