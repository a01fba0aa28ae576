"""Session leases over HTTP (docs/service.md, "Leases: no orphan session"): a real `flockcal serve` on the
built-in simulator; a session started with `lease_s` ends that long after its client last renewed it,
with the reason stored; renewing keeps it; a session without a lease, a stopped one and a malformed lease
are refused with a reason and change nothing.
"""

from __future__ import annotations

import httpx
import pytest

from flockcal.server.settings import Settings
from server_helpers import ServerProcess, free_port, manual_service, run_clock, wait_connected

LEASE_S = 2.0
WATCH_S = 0.5  # docs/service.md: the lease watcher looks twice a second


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


def test_a_session_whose_client_stops_renewing_ends_after_its_lease_with_the_reason(tmp_path):
    # On the service's own clock, moved by the test (server_helpers.manual_service): the lease is judged to
    # the tenth of a second however slowly a loaded machine runs the stop.
    settings = Settings(device="sim://lease?birds=4&model=linkage&motion=exercise&rate=60", birds=4,
                        http_port=free_port(), data_dir=tmp_path)
    with manual_service(settings) as (srv, clock):
        url = srv.url
        s = start(url, lease_s=LEASE_S, profile="kiosk")
        assert s["lease_s"] == LEASE_S and s["profile"] == "kiosk"
        # Renewed every half lease for three leases' time: still live, each renewal good for a whole lease.
        for _ in range(7):
            r = httpx.post(f"{url}/api/sessions/{s['id']}/lease")
            assert r.status_code == 200, r.text
            assert r.json()["lease_s"] == LEASE_S and r.json()["expires_in_s"] == pytest.approx(LEASE_S)
            run_clock(clock, LEASE_S / 2, dt=0.1)
        assert row(url, s["id"])["state"] == "live"
        # Tried: the client goes quiet (its last renewal a half lease ago). Live until the lease runs out ...
        run_clock(clock, LEASE_S / 2 - 0.1, dt=0.1)
        assert row(url, s["id"])["state"] == "live"

        def ended() -> bool:
            got = row(url, s["id"])
            return got["state"] == "stopped" and "lease" in (got.get("note") or "")

        # ... and ended by the watcher's next look after it has (it looks twice a second).
        run_clock(clock, 0.1 + WATCH_S + 0.05, dt=0.05, until=ended)
        events = httpx.get(f"{url}/api/sessions/{s['id']}/events").json()["events"]
        assert any(e.get("reason") == "lease_expired" for e in events), events
        # The next session starts at once: nothing is left live.
        nxt = start(url)
        assert httpx.post(f"{url}/api/sessions/{nxt['id']}/stop", timeout=30).status_code == 200


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
