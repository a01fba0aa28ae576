"""REST API promises of `flockcal serve`: bad input gets a clear 4xx and changes nothing; tokens and
roles guard every mutating request; names and ids cannot reach outside the data directory.

A real uvicorn on a free loopback port, with the driver reading the built-in sim:// tracker.
"""

from __future__ import annotations

import sqlite3

import httpx
import pytest

from flockcal.server.errors import ConfigError
from flockcal.server.settings import Settings
from server_helpers import ServerThread, free_port, wait_connected

ADMIN, READ, KIOSK = "admin-token-123", "read-token-456", "kiosk-token-789"


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    data = tmp_path_factory.mktemp("serve")
    settings = Settings(device="sim://api?birds=4&model=linkage&motion=exercise&rate=60", birds=4,
                        http_port=free_port(), data_dir=data, token=ADMIN, read_token=READ, kiosk_token=KIOSK,
                        max_body_bytes=4096)
    with ServerThread(settings) as srv:
        wait_connected(srv.url, token=READ)
        yield srv


def hdr(token):
    return {"Authorization": f"Bearer {token}"}


def db_rows(server) -> dict:
    # Read the SQLite file itself (a second connection), as an operator would. Tracker events are the
    # tracker's, not a request's: the simulated linkage crosses the hemisphere now and then, and on a
    # loaded machine such an event can land between a test's two counts.
    with sqlite3.connect(server.settings.data_dir / "flockcal.sqlite3") as db:
        rows = {t: db.execute(f"SELECT COUNT(*) FROM {t}").fetchone()[0] for t in ("sessions", "residuals")}
        rows["events"] = db.execute("SELECT COUNT(*) FROM events WHERE type != 'tracker'").fetchone()[0]
        return rows


def assert_error(r: httpx.Response, status: int, *words: str):
    assert r.status_code == status, r.text
    body = r.json()
    assert isinstance(body["detail"], str) and body["detail"], body
    for w in words:
        assert w.lower() in body["detail"].lower(), body


@pytest.mark.parametrize("case", ["malformed_json", "wrong_type", "missing_field", "unknown_field",
                                  "traversal_name", "bad_hierarchy", "cyclic_hierarchy", "unknown_root",
                                  "root_off_the_hierarchy", "oversized", "oversized_chunked"])
def test_bad_session_requests_get_4xx_and_change_nothing(server, case):
    before = db_rows(server)
    url = server.url + "/api/sessions"
    if case == "malformed_json":  # a body cut short
        r = httpx.post(url, content=b'{"performer": "ann"', headers={**hdr(ADMIN), "content-type": "application/json"})
        assert_error(r, 400, "not valid JSON")
    elif case == "wrong_type":  # performer as a number
        r = httpx.post(url, json={"performer": 42}, headers=hdr(ADMIN))
        assert_error(r, 422, "performer")
    elif case == "missing_field":  # no performer at all
        r = httpx.post(url, json={}, headers=hdr(ADMIN))
        assert_error(r, 422, "performer")
    elif case == "unknown_field":  # a typo'd field name
        r = httpx.post(url, json={"performer": "ann", "heirarchy": {}}, headers=hdr(ADMIN))
        assert_error(r, 422, "heirarchy", "unknown field")
    elif case == "traversal_name":  # a name that walks out of the data directory
        r = httpx.post(url, json={"performer": "../../etc/passwd"}, headers=hdr(ADMIN))
        assert_error(r, 422, "performer")
    elif case == "bad_hierarchy":  # a hierarchy naming a sensor that does not exist
        r = httpx.post(url, json={"performer": "ann", "hierarchy": {"nope": "pelvis"}}, headers=hdr(ADMIN))
        assert_error(r, 400, "unknown sensor")
    elif case == "cyclic_hierarchy":  # two sensors each other's parent (the solver's one check of a tree)
        a, b, c, d = httpx.get(server.url + "/api/status", headers=hdr(READ)).json()["sensors"]
        r = httpx.post(url, json={"performer": "ann", "hierarchy": {b: c, c: b, d: a}}, headers=hdr(ADMIN))
        assert_error(r, 400, "cycle", b, c)
    elif case == "root_off_the_hierarchy":  # a root the hierarchy gives a parent
        a, b, c, d = httpx.get(server.url + "/api/status", headers=hdr(READ)).json()["sensors"]
        r = httpx.post(url, json={"performer": "ann", "hierarchy": {b: a, c: b, d: c}, "root": c}, headers=hdr(ADMIN))
        assert_error(r, 400, "root", repr(a), repr(c))
    elif case == "unknown_root":  # a root that is not a sensor
        r = httpx.post(url, json={"performer": "ann", "root": "tail"}, headers=hdr(ADMIN))
        assert_error(r, 400, "root")
    elif case == "oversized":  # 10 kB of performer name against a 4 kB limit
        r = httpx.post(url, json={"performer": "a" * 10_000}, headers=hdr(ADMIN))
        assert_error(r, 413, "too large")
    elif case == "oversized_chunked":  # the same without a Content-Length header (chunked upload)
        body = (b'{"performer": "' + b"a" * 10_000 + b'"}',)
        r = httpx.post(url, content=iter(body), headers={**hdr(ADMIN), "content-type": "application/json"})
        assert_error(r, 413, "too large")
    assert db_rows(server) == before


@pytest.mark.parametrize("token,status", [(None, 401), ("wrong-token-000", 401), (READ, 403)])
def test_mutating_requests_need_the_right_token(server, token, status):
    before = db_rows(server)
    headers = hdr(token) if token else {}
    r = httpx.post(server.url + "/api/sessions", json={"performer": "ann"}, headers=headers)
    assert_error(r, status, "token")
    if status == 401:
        assert r.headers.get("www-authenticate") == "Bearer"
    assert db_rows(server) == before


def test_reads_need_a_token_and_the_read_token_suffices(server):
    assert httpx.get(server.url + "/api/status").status_code == 401  # no token
    r = httpx.get(server.url + "/api/status", headers=hdr(READ))
    assert r.status_code == 200 and r.json()["birds"] == 4


def test_unknown_and_malicious_ids_get_4xx(server):
    before = db_rows(server)
    # An id that looks right but does not exist.
    assert_error(httpx.get(server.url + "/api/sessions/20200101-000000-abcdef", headers=hdr(READ)), 404, "no session")
    assert_error(httpx.post(server.url + "/api/sessions/20200101-000000-abcdef/stop", headers=hdr(ADMIN)), 404)
    assert_error(httpx.delete(server.url + "/api/sessions/20200101-000000-abcdef", headers=hdr(ADMIN)), 404)
    # Path traversal through the id, percent-encoded so the client does not normalise it away.
    r = httpx.get(server.url + "/api/sessions/..%2F..%2Fflockcal.sqlite3/take", headers=hdr(READ))
    assert r.status_code == 404 and r.headers["content-type"] == "application/json"
    assert_error(httpx.get(server.url + "/api/sessions/..flockcal.sqlite3/take", headers=hdr(READ)), 400,
                 "not a session id")
    assert_error(httpx.get(server.url + "/api/sessions/a%00b", headers=hdr(READ)), 400)
    # Wrong types in the query string.
    assert httpx.get(server.url + "/api/events?since=soon", headers=hdr(READ)).status_code == 422
    assert db_rows(server) == before


def test_kiosk_token_starts_and_stops_but_cannot_delete(server):
    r = httpx.post(server.url + "/api/sessions", json={"performer": "guest 1"}, headers=hdr(KIOSK))
    assert r.status_code == 201, r.text
    sid = r.json()["id"]
    try:
        # A second session while one is live: a conflict naming the live one.
        assert_error(httpx.post(server.url + "/api/sessions", json={"performer": "guest 2"}, headers=hdr(KIOSK)),
                     409, sid)
        assert_error(httpx.delete(server.url + f"/api/sessions/{sid}", headers=hdr(KIOSK)), 403, "admin")
        assert_error(httpx.post(server.url + f"/api/sessions/{sid}/resolve", headers=hdr(KIOSK)), 403)
    finally:
        r = httpx.post(server.url + f"/api/sessions/{sid}/stop", headers=hdr(KIOSK))
    assert r.status_code == 200 and r.json()["state"] == "stopped"
    assert_error(httpx.post(server.url + f"/api/sessions/{sid}/stop", headers=hdr(KIOSK)), 409, "not live")
    assert httpx.delete(server.url + f"/api/sessions/{sid}", headers=hdr(ADMIN)).status_code == 204
    assert httpx.get(server.url + f"/api/sessions/{sid}", headers=hdr(READ)).status_code == 404
    assert not (server.settings.data_dir / "recordings" / f"{sid}.frames").exists()


def test_cross_site_pages_cannot_change_anything(server):
    # A page on another site posting with the admin token a browser might hold: refused, nothing changes.
    before = db_rows(server)
    r = httpx.post(server.url + "/api/sessions", json={"performer": "ann"},
                   headers={**hdr(ADMIN), "Origin": "http://evil.example"})
    assert_error(r, 403, "cors-origin")
    assert db_rows(server) == before
    # The service's own pages (same origin) may.
    r = httpx.post(server.url + "/api/sessions", json={"performer": "ann"},
                   headers={**hdr(ADMIN), "Origin": server.url})
    assert r.status_code == 201
    assert httpx.post(server.url + f"/api/sessions/{r.json()['id']}/stop", headers=hdr(ADMIN)).status_code == 200


def test_cors_is_closed_by_default(server):
    r = httpx.options(server.url + "/api/sessions", headers={
        "Origin": "http://evil.example", "Access-Control-Request-Method": "POST"})
    assert "access-control-allow-origin" not in r.headers


def test_pages_and_api_docs_are_served(server):
    assert httpx.get(server.url + "/").status_code == 200
    assert httpx.get(server.url + "/kiosk").status_code == 200
    spec = httpx.get(server.url + "/openapi.json").json()
    for path in ("/api/status", "/api/sessions", "/api/sessions/{id}", "/api/sessions/{id}/stop",
                 "/api/sessions/{id}/result", "/api/sessions/{id}/residuals", "/api/sessions/{id}/events",
                 "/api/sessions/{id}/resolve"):
        assert path in spec["paths"], path


def test_public_address_without_token_is_refused():
    with pytest.raises(ConfigError, match="--token"):
        Settings(host="0.0.0.0", data_dir="/tmp/unused").check()
    Settings(host="0.0.0.0", token="long-enough-token", data_dir="/tmp/unused").check()


def test_simulator_control_needs_admin_and_a_known_sensor(server):
    assert_error(httpx.post(server.url + "/api/simulator/slip", json={"sensor": "s1", "distance_m": 0.02},
                            headers=hdr(KIOSK)), 403)
    assert_error(httpx.post(server.url + "/api/simulator/slip", json={"sensor": "nobody", "distance_m": 0.02},
                            headers=hdr(ADMIN)), 400, "no sensor")
    assert_error(httpx.post(server.url + "/api/simulator/motion", json={"routine": "moonwalk"},
                            headers=hdr(ADMIN)), 400, "routine")
