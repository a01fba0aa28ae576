"""Session leases over HTTP (docs/service.md, "Leases: no orphan session"): a real `flockcal serve` on the
built-in simulator; a session started with `lease_s` ends that long after its client last renewed it,
with the reason stored; renewing keeps it; a session without a lease, a stopped one and a malformed lease
are refused with a reason and change nothing.
"""

from __future__ import annotations

import time

import httpx
import pytest

from server_helpers import ServerProcess, free_port, wait_connected

LEASE_S = 2.0
# The watcher looks twice a second; a loaded machine's stop (final fit, result stored) gets 10 s more.
ENDED_WITHIN_S = LEASE_S + 0.5 + 10.0


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    data = tmp_path_factory.mktemp("lease")
    proc = ServerProcess(["--device", "sim://lease?birds=4&model=linkage&motion=exercise&rate=60", "--birds", "4",
                          "--data-dir", str(data)], free_port(), log_path=data / "serve.log").start()
    wait_connected(proc.url)
    yield proc
    proc.stop()


def start(url: str, **body) -> dict:
    r = httpx.post(f"{url}/api/sessions", json={"performer": "Guest", **body}, timeout=30)
    assert r.status_code == 201, r.text
    return r.json()


def row(url: str, sid: str) -> dict:
    return httpx.get(f"{url}/api/sessions/{sid}").json()


def test_a_session_whose_client_stops_renewing_ends_after_its_lease_with_the_reason(server):
    s = start(server.url, lease_s=LEASE_S, profile="kiosk")
    assert s["lease_s"] == LEASE_S and s["profile"] == "kiosk"
    began = time.monotonic()
    # Renewed for three leases' time: still live.
    while time.monotonic() - began < 3 * LEASE_S:
        sent = time.monotonic()
        r = httpx.post(f"{server.url}/api/sessions/{s['id']}/lease")
        assert r.status_code == 200, r.text
        assert r.json()["lease_s"] == LEASE_S and 0 < r.json()["expires_in_s"] <= LEASE_S
        time.sleep(LEASE_S / 4)
    assert row(server.url, s["id"])["state"] == "live"
    # Tried: the client goes quiet.
    quiet = time.monotonic()
    while not ((got := row(server.url, s["id"]))["state"] == "stopped" and "lease" in (got.get("note") or "")):
        assert time.monotonic() - quiet < ENDED_WITHIN_S, got
        time.sleep(0.1)
    assert time.monotonic() - sent >= LEASE_S  # not before the lease ran out (renewed after `sent`)
    events = httpx.get(f"{server.url}/api/sessions/{s['id']}/events").json()["events"]
    assert any(e.get("reason") == "lease_expired" for e in events), events
    # The next session starts at once: nothing is left live.
    nxt = start(server.url)
    assert httpx.post(f"{server.url}/api/sessions/{nxt['id']}/stop", timeout=30).status_code == 200


def test_renewing_what_has_no_lease_or_is_not_live_is_refused_and_a_bad_lease_never_starts(server):
    s = start(server.url)  # an operator's session: no lease
    assert s.get("lease_s") is None
    r = httpx.post(f"{server.url}/api/sessions/{s['id']}/lease")
    assert r.status_code == 409 and "without a lease" in r.json()["detail"]
    # Tried: a lease of 0.5 s (below 1), a negative one, a string: 422, and the live session is untouched.
    for bad in (0.5, -3, "long"):
        r = httpx.post(f"{server.url}/api/sessions", json={"performer": "Guest", "lease_s": bad})
        assert r.status_code == 422, (bad, r.text)
    assert httpx.get(f"{server.url}/api/sessions").json()["live"] == s["id"]
    assert httpx.post(f"{server.url}/api/sessions/{s['id']}/stop", timeout=30).status_code == 200
    r = httpx.post(f"{server.url}/api/sessions/{s['id']}/lease")
    assert r.status_code == 409 and "not live" in r.json()["detail"]
