"""What a client gets from a session while it records, over HTTP from a real `flockcal serve` (a child
process on the built-in simulator, 16 birds at 144 Hz): the raw download read by a slow client is a whole
.fobraw of exactly the length it declares; the live result lists the slips the service has reported, as the
stored result does after the stop; the session row carries the tracker's rate.
"""

from __future__ import annotations

import socket
import subprocess
import sys
from pathlib import Path

import httpx
import pytest

from flockcal.drivers.recording import MAGIC, read_recording
from server_helpers import ServerProcess, free_port, start_session, wait_connected
from service_process import wait_for

RATE_HZ = 144
SLIPPED = "r_shin"  # found and named in every run of the service slip benchmark (tests/test_server_slip.py)
SLIP_AFTER_S = 20.0  # the slip monitor's promise holds for slips 20 s or more into a session


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    data = tmp_path_factory.mktemp("recording")
    srv = ServerProcess(["--device", f"sim://?birds=16&motion=exercise&rate={RATE_HZ}&baud=921600&seed=4",
                         "--data-dir", str(data), "--fast-init"], free_port(), log_path=data / "serve.log")
    srv.start()
    try:
        wait_connected(srv.url)
        sid = start_session(srv.url)
        yield srv, sid, data / "recordings" / f"{sid}.fobraw"
    finally:
        srv.stop()


def session_time(srv) -> float:
    return httpx.get(srv.url + "/api/status", timeout=30).json()["session"]["time_s"]


def slow_get(url: str, path: str) -> tuple[socket.socket, dict, bytes]:
    """A GET whose client keeps a 4 KB receive window and reads the head only: the server can be at most
    its send buffer (256 kB) ahead of what the client has read."""
    u = httpx.URL(url)
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    sock.settimeout(30)
    sock.connect((u.host, u.port))
    sock.sendall(f"GET {path} HTTP/1.1\r\nHost: {u.host}\r\nConnection: close\r\n\r\n".encode())
    data = b""
    while b"\r\n\r\n" not in data:
        part = sock.recv(1024)
        assert part, "the server closed the connection before the headers"
        data += part
    head, _, rest = data.partition(b"\r\n\r\n")
    lines = head.decode("latin-1").split("\r\n")
    headers = {k.strip().lower(): v.strip() for k, v in (line.split(":", 1) for line in lines[1:])}
    headers[":status"] = lines[0].split(" ", 2)[1]
    return sock, headers, rest


def chunk_ends(data: bytes) -> list[int]:
    """Where each chunk of a .fobraw ends, parsed by the recording reader from a copy of the file."""
    rec = read_recording_bytes(data)
    header = len(MAGIC) + 4 + int.from_bytes(data[len(MAGIC):len(MAGIC) + 4], "little") + 4
    ends, pos = [header], header
    for c in rec.chunks:
        pos += 2 + 1 + 1 + 8 + 4 + len(c.payload) + 4  # sync, kind, port, time, length; payload; CRC
        ends.append(pos)
    return ends


def read_recording_bytes(data: bytes, name: str = "copy.fobraw"):
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / name
        path.write_bytes(data)
        return read_recording(path)


def test_a_slow_reader_gets_the_live_raw_recording_whole_with_its_declared_length(live, tmp_path):
    """Tried as issue #29 did: GET /raw 25 s into a session by a slow client. The body stopped at
    1,835,008 of the 1,850,061 bytes its Content-Length declared (the file grew while it was sent).
    Here the client reads nothing until the recording has grown 256 kB past what was declared."""
    srv, sid, raw = live
    wait_for(lambda: raw.exists() and raw.stat().st_size > 1_000_000, 120, "a 1 MB raw recording")
    before = raw.stat().st_size
    sock, headers, body = slow_get(srv.url, f"/api/sessions/{sid}/raw")
    try:
        assert headers[":status"] == "200", headers
        declared = int(headers["content-length"])
        assert "chunked" not in headers.get("transfer-encoding", "")
        wait_for(lambda: raw.stat().st_size > declared + 256 * 1024, 60, "the recording growing 256 kB")
        while len(body) < declared:
            part = sock.recv(65536)
            if not part:
                break
            body += part
    finally:
        sock.close()
    assert len(body) == declared, f"got {len(body)} of the {declared} bytes declared"
    # The recording as it stood when asked: the file's own first bytes, ending on a whole chunk at or
    # after the last whole chunk the file held just before the request.
    on_disk = raw.read_bytes()
    assert body == on_disk[:declared]
    ends = chunk_ends(on_disk)
    assert declared in ends and declared >= max(e for e in ends if e <= before)
    assert not read_recording_bytes(body).truncated
    # What a user does with it: `flockcal convert` without --salvage, one take of 16 sensors.
    (tmp_path / "live.fobraw").write_bytes(body)
    run = subprocess.run([sys.executable, "-m", "flockcal", "convert", "live.fobraw", "-o", "live.npz"], cwd=tmp_path,
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0 and "of 16 sensors" in run.stderr, run.stderr


def test_the_session_row_carries_the_tracker_rate(live):
    # Tried: GET /api/sessions during a session started without --rate: its row read rate_hz null.
    srv, sid, _ = live
    status = httpx.get(srv.url + "/api/status", timeout=30).json()
    row = httpx.get(srv.url + f"/api/sessions/{sid}", timeout=30).json()
    listed = {r["id"]: r for r in httpx.get(srv.url + "/api/sessions", timeout=30).json()["sessions"]}
    assert row["rate_hz"] == RATE_HZ == status["rate_hz"] and listed[sid]["rate_hz"] == RATE_HZ, row


def test_the_live_result_lists_the_slips_reported_as_the_stored_one_does(live):
    """Tried: a slip the service reported (event, alert, re-fit), then GET …/result while live: it had
    `slip_events: []`, and only the stored result after the stop listed the slip."""
    srv, sid, _ = live
    wait_for(lambda: session_time(srv) >= SLIP_AFTER_S, 120, f"{SLIP_AFTER_S} s of session")
    r = httpx.post(srv.url + "/api/simulator/slip", json={"sensor": SLIPPED, "distance_m": 0.03}, timeout=30)
    assert r.status_code == 200, r.text

    def reported():
        events = httpx.get(srv.url + f"/api/sessions/{sid}/events", timeout=30).json()["events"]
        return [e for e in events if e["type"] == "slip"]

    events = wait_for(reported, 30, f"the service reporting the {SLIPPED} slip")
    result = httpx.get(srv.url + f"/api/sessions/{sid}/result", timeout=30).json()
    listed = result["slip_events"]
    assert len(listed) >= len(events) >= 1
    assert [(e["sensor"], e["time_s"], e["detected_s"]) for e in listed[:len(events)]] == \
        [(e["sensor"], e["time_s"], e["detected_s"]) for e in events]
    assert any(SLIPPED in [e["sensor"], *e["candidates"]] for e in listed), listed

    r = httpx.post(srv.url + f"/api/sessions/{sid}/stop", timeout=60)
    assert r.status_code == 200, r.text
    stored = httpx.get(srv.url + f"/api/sessions/{sid}/result", timeout=30).json()["slip_events"]
    assert stored[:len(listed)] == listed  # the live list, field for field, is what the stored one holds
