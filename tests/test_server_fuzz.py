"""No 500 is reachable from a request: every operation in the service's own OpenAPI document, with
every parameter and body field given hostile values, answers below 500 with a readable JSON `detail`.

A hand-written, deterministic fuzz (same cases every run, about 800 requests) against a real uvicorn
on loopback in the default no-token mode, so every request reaches its handler with the admin's rights.
"""

from __future__ import annotations

import json
import urllib.parse

import httpx
import pytest

from flockcal.server.settings import Settings
from server_helpers import ServerThread, free_port, wait_connected

# Values a careless client or an attacker sends; as text (query and path) and as JSON (bodies).
TEXT = ["", " ", "a\n", "\x00", "9223372036854775808", "-9223372036854775809", "1" + "0" * 400, "-1", "0",
        "1e400", "nan", "-inf", "ü\u202e", "x" * 5000, "../../etc/passwd", "..", "[]", "{}", "true", "%",
        "20200101-000000-abcdef"]
JSON_VALUES = [None, True, 0, -1, 10**400, 2**63, -(2**63) - 1, 1e308, "", "a\n", "x" * 5000, "\u202e",
               [], {}, [[[[[[[[[[1]]]]]]]]]], {"a": {"b": {"c": {}}}}]
RAW_BODIES = [b"", b"null", b"[]", b"{}", b'"x"', b"\xff\xfe\x00", b"{" * 5000, b"[" * 30000 + b"]" * 30000,
              b'{"a":' * 3000 + b"1" + b"}" * 3000, b'{"performer": "x"' * 100, b"1" + b"0" * 5000]


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    settings = Settings(device="sim://fuzz?birds=4&model=linkage&motion=exercise&rate=60", birds=4,
                        http_port=free_port(), data_dir=tmp_path_factory.mktemp("fuzz"))
    with ServerThread(settings) as srv:
        wait_connected(srv.url)
        # One real, stopped session, so ids also reach the handlers behind the id check.
        sid = httpx.post(srv.url + "/api/sessions", json={"performer": "Fuzz"}).json()["id"]
        httpx.post(srv.url + f"/api/sessions/{sid}/stop", timeout=30)
        yield srv, sid


def operations(spec: dict):
    for path, item in spec["paths"].items():
        for method, op in item.items():
            if method in ("get", "post", "delete", "put", "patch"):
                yield path, method.upper(), op


def body_schema(spec: dict, op: dict) -> dict | None:
    content = (op.get("requestBody") or {}).get("content", {})
    schema = (content.get("application/json") or {}).get("schema")
    if schema and "$ref" in schema:
        schema = spec["components"]["schemas"][schema["$ref"].rsplit("/", 1)[-1]]
    return schema


def cases(spec: dict, sid: str):
    """(method, url path with query, body bytes or None) for every operation × hostile value."""
    for path, method, op in operations(spec):
        params = op.get("parameters", [])
        good_path = {p["name"]: (sid if p["name"] == "id" else "Fuzz") for p in params if p["in"] == "path"}
        fill = lambda values: path.format(**{k: urllib.parse.quote(v, safe="") for k, v in values.items()})
        yield method, fill(good_path), b"{}" if method == "POST" else None
        for p in params:
            for value in TEXT:
                if p["in"] == "path":
                    yield method, fill({**good_path, p["name"]: value}), None
                elif p["in"] == "query":
                    yield method, fill(good_path) + "?" + urllib.parse.urlencode({p["name"]: value}), None
        if method in ("POST", "PUT", "PATCH"):
            for raw in RAW_BODIES:
                yield method, fill(good_path), raw
            schema = body_schema(spec, op) or {}
            for field in (schema.get("properties") or {"performer": {}}):
                for value in JSON_VALUES:
                    yield method, fill(good_path), json.dumps({"performer": "Fuzz", field: value}).encode()


def test_no_request_gets_a_500(server):
    srv, sid = server
    spec = httpx.get(srv.url + "/openapi.json").json()
    assert len(list(operations(spec))) >= 20  # the whole API, not a corner of it
    failures, seen, codes = [], 0, {}
    with httpx.Client(base_url=srv.url, timeout=60) as client:
        for method, url, body in cases(spec, sid):
            headers = {"content-type": "application/json"} if body is not None else {}
            r = client.request(method, url, content=body, headers=headers)
            seen += 1
            if r.status_code >= 500:
                failures.append((method, url[:120], (body or b"")[:60], r.status_code, r.text[:200]))
            elif r.status_code >= 400:
                detail = r.json().get("detail")
                if not isinstance(detail, str) or not detail:
                    failures.append((method, url[:120], (body or b"")[:60], r.status_code, "no readable detail"))
            codes[r.status_code] = codes.get(r.status_code, 0) + 1
            live = srv.service.sessions.live_id()
            if live is not None:  # a fuzzed start that was valid: stop it, so the next starts are tried too
                client.post(f"/api/sessions/{live}/stop", timeout=30)
        # The service still serves after all of it.
        assert client.get("/api/status").status_code == 200
    assert seen > 700 and len(codes) >= 5, codes  # many requests, and they got past the first checks
    assert not failures, f"{len(failures)} of {seen} requests failed, first ones: {failures[:8]}"
