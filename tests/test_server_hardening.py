"""Hardening of the live service (issue #16), probed as an attacker and as a careless client would:
foreign Host names (DNS rebinding), websocket messages that used to close the socket, stalled and
tokenless websocket clients, numbers and nesting that used to give a 500, the failed-token back-off.

A real uvicorn on a free loopback port reading the built-in sim:// tracker; websockets and raw sockets.
"""

from __future__ import annotations

import asyncio
import io
import json
import socket
import struct

import httpx
import numpy as np
import pytest
import websockets

from flockcal.server.settings import Settings
from server_helpers import ServerThread, free_port, wait_connected
from service_process import wait_for

ADMIN, READ = "admin-token-123", "read-token-456"
def sim(name: str) -> str:
    # Each server its own simulator name: one name is one simulated tracker in this process.
    return f"sim://{name}?birds=4&model=linkage&motion=exercise&rate=60"


@pytest.fixture(scope="module")
def open_server(tmp_path_factory):
    """The default mode: loopback, no token; a small send buffer and a short drop timeout so a stalled
    client is dropped in seconds."""
    settings = Settings(device="sim://hardened?birds=16&motion=exercise&rate=144&baud=921600", birds=16,
                        http_port=free_port(), data_dir=tmp_path_factory.mktemp("open"), ws_send_timeout_s=1.5,
                        send_buffer_bytes=32768)
    with ServerThread(settings) as srv:
        wait_connected(srv.url)
        yield srv


def ws_url(server, query: str = "") -> str:
    return server.url.replace("http://", "ws://") + "/ws/live" + query


def sessions(server) -> int:
    return server.service.store.counts()["sessions"]


# --- 1. DNS rebinding --------------------------------------------------------------------------------
def test_a_page_under_a_foreign_host_name_reaches_nothing(open_server):
    srv = open_server
    port = srv.settings.http_port
    evil = {"Host": f"evil.example:{port}", "Origin": f"http://evil.example:{port}"}
    before = sessions(srv)
    # What a rebound page sends: its own name as Host and Origin (so Origin == Host), no token.
    r = httpx.post(srv.url + "/api/sessions", json={"performer": "x"}, headers=evil)
    assert r.status_code == 400 and "--allow-host evil.example" in r.json()["detail"], r.text
    assert sessions(srv) == before
    for method, path in (("GET", "/api/status"), ("GET", "/api/sessions"), ("POST", "/api/simulator/slip"),
                         ("DELETE", "/api/sessions/20200101-000000-abcdef"), ("GET", "/")):
        r = httpx.request(method, srv.url + path, headers=evil, json={} if method == "POST" else None)
        assert r.status_code == 400, (method, path, r.status_code)

    async def rebound_socket():
        # The page's own name in the URL (so in Host), the socket to loopback: what a rebound name resolves to.
        async with websockets.connect(f"ws://evil.example:{port}/ws/live",
                                      additional_headers={"Origin": f"http://evil.example:{port}"},
                                      sock=socket.create_connection(("127.0.0.1", port))):
            pass

    # The handshake itself is refused: no hello, no data.
    with pytest.raises(websockets.InvalidStatus) as info:
        asyncio.run(rebound_socket())
    assert info.value.response.status_code == 403
    # Loopback names keep working, with or without a port, with a trailing dot, IPv6 form.
    for host in (f"localhost:{port}", f"127.0.0.1:{port}", "localhost", f"LOCALHOST.:{port}", f"127.0.0.2:{port}"):
        assert httpx.get(srv.url + "/api/status", headers={"Host": host}).status_code == 200, host


def test_allow_host_lets_a_named_host_in(tmp_path):
    from flockcal.cli import build_parser
    from flockcal.commands.serve import settings_from_args

    # The option as a user gives it on the command line, through to the running app.
    args = build_parser().parse_args(["serve", "--device", sim("allowhost"), "--birds", "4", "--allow-host", "stage-pc.lan",
                                      "--http-port", str(free_port()), "--data-dir", str(tmp_path)])
    settings = settings_from_args(args)
    with ServerThread(settings) as srv:
        port = settings.http_port
        assert httpx.get(srv.url + "/api/status", headers={"Host": f"stage-pc.lan:{port}"}).status_code == 200
        assert httpx.get(srv.url + "/api/status", headers={"Host": f"stage-pc.lan.evil.example:{port}"}).status_code == 400


# --- 6. websocket messages that used to close the socket ------------------------------------------------
def test_any_bad_websocket_message_gets_an_error_and_the_socket_stays_open(open_server):
    bad = [
        b"\x00\x01binary",  # a binary frame (was KeyError 'text')
        '{"type": "subscribe", "rate_hz": 1' + "0" * 400 + "}",  # an integer past float (was OverflowError)
        "[" * 30000 + "]" * 30000,  # deep nesting (was RecursionError)
        '{"type": "subscribe", "content": [[[["status"]]]]}',  # nesting inside a field
        '{"type": {"a": 1}}',  # a type that is not a string
        '{"type": "subscribe", "rate_hz": "fast"}',
        '"just a string"',
        "not json at all",
    ]

    async def main():
        async with websockets.connect(ws_url(open_server), max_size=None) as ws:
            assert json.loads(await ws.recv())["type"] == "hello"
            replies = []
            for message in bad:
                await ws.send(message)
                replies.append(json.loads(await asyncio.wait_for(ws.recv(), 5)))
            await ws.send(json.dumps({"type": "subscribe", "rate_hz": 5, "content": ["status"]}))
            replies.append(json.loads(await asyncio.wait_for(ws.recv(), 5)))
            return replies

    *errors, ok = asyncio.run(main())
    assert [e["type"] for e in errors] == ["error"] * len(bad), errors
    assert "binary" in errors[0]["message"] and "rate_hz" in errors[1]["message"]
    assert "nested too deeply" in errors[2]["message"] and "nested too deeply" in errors[3]["message"]
    assert ok["type"] == "subscribed"


# --- 2. stalled clients are cut off -------------------------------------------------------------------
TCP_ESTABLISHED = 1  # linux/tcp_states.h


def tcp_state(sock: socket.socket) -> int:
    return struct.unpack("B", sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_INFO, 8)[:1])[0]


def test_a_stalled_client_is_dropped_and_its_socket_closed(open_server):
    srv = open_server
    hub = srv.service.hub

    async def main():
        clients_before, dropped_before = hub.clients, hub.dropped_slow
        sock = socket.socket()
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # a tiny window: the server's sends block soon
        sock.connect(("127.0.0.1", srv.settings.http_port))
        # max_queue=1: the client library stops reading once one message waits, like a frozen page.
        ws = await websockets.connect(ws_url(srv), sock=sock, max_queue=1)
        await ws.send(json.dumps({"type": "subscribe", "rate_hz": 1000,
                                  "content": ["status", "fit", "residuals", "events", "pose"]}))
        await asyncio.to_thread(wait_for, lambda: hub.dropped_slow != dropped_before, 30, "the stalled client dropped")
        assert hub.dropped_slow == dropped_before + 1, "the stalled client was dropped once"
        # Once dropped, the connection is gone on both sides: the server reset it (the client's kernel sees
        # it closed though the client still reads nothing) and the client no longer holds a slot.
        await asyncio.to_thread(wait_for, lambda: tcp_state(sock) != TCP_ESTABLISHED and hub.clients <= clients_before,
                                30, "the dropped client's connection closed and its slot freed")
        state, clients = tcp_state(sock), hub.clients
        ws.transport.abort()
        return state, clients, clients_before

    state, clients, clients_before = asyncio.run(main())
    assert state != TCP_ESTABLISHED, "the server left the stalled client's connection established"
    # (At most as many as before: a client of an earlier test on this server may still have been leaving.)
    assert clients <= clients_before


# --- 3. tokenless sockets cannot take the slots ----------------------------------------------------------
def test_tokenless_sockets_cannot_fill_the_slots_of_clients_with_a_token(tmp_path):
    settings = Settings(device=sim("slots"), birds=4, http_port=free_port(), data_dir=tmp_path, token=ADMIN, read_token=READ,
                        ws_max_clients=3)
    with ServerThread(settings) as srv:
        wait_connected(srv.url, token=READ)

        async def subscribed(query: str, token: str | None = None):
            ws = await websockets.connect(ws_url(srv, query))
            await ws.recv()  # hello
            sub = {"type": "subscribe", "rate_hz": 2, "content": ["status"]}
            if token:
                sub["token"] = token
            await ws.send(json.dumps(sub))
            return ws, json.loads(await asyncio.wait_for(ws.recv(), 5))

        async def main():
            # 40 sockets that never give a token: more than the pool of sockets waiting for one holds.
            idle = []
            for _ in range(40):
                ws = await websockets.connect(ws_url(srv))
                assert json.loads(await ws.recv())["type"] == "hello"
                idle.append(ws)
            # A read-token client still gets in, by URL and by subscribe message, up to the read limit.
            a, first = await subscribed(f"?token={READ}")
            b, second = await subscribed("", READ)
            c, third = await subscribed(f"?token={READ}")
            with pytest.raises(websockets.ConnectionClosed) as info:
                await subscribed(f"?token={READ}")  # the fourth read client: the read slots are full
            # ...while the admin's own slots are untouched by the read clients.
            d, admin = await subscribed(f"?token={ADMIN}")
            # The idle sockets that waited longest gave way, told why, with "try again later".
            async def told(ws) -> bool:
                try:
                    msg = json.loads(await asyncio.wait_for(ws.recv(), 1.0))
                except asyncio.TimeoutError:
                    return False
                assert msg["type"] == "error"
                await ws.wait_closed()
                # (Sockets still waiting after 10 s are closed for that, with 1008.)
                if "waiting for a token" not in msg["message"]:
                    return False
                assert ws.close_code == 1013
                return True

            evicted = sum(await asyncio.gather(*[told(ws) for ws in idle]))
            for ws in (*idle, a, b, c, d):
                await ws.close()
            return evicted, [first, second, third, admin], info.value

        evicted, oks, full = asyncio.run(main())
    assert [m["type"] for m in oks] == ["subscribed"] * 4, oks
    assert full.rcvd.code == 1013  # not a 403 handshake: the client may retry
    # The pool is bounded: at least the 8 sockets beyond 32 and the one the message-token client needed.
    assert evicted >= 9


# --- 4, 5. numbers and nesting that used to give a 500 -----------------------------------------------
def test_huge_numbers_and_deep_nesting_get_a_4xx_and_the_connection_lives_on(open_server):
    srv = open_server
    with httpx.Client(base_url=srv.url) as client:
        for path in ("/api/events?since=9223372036854775808", "/api/events?since=1" + "0" * 400,
                     "/api/events?limit=99999999999999999999"):
            r = client.get(path)
            assert r.status_code == 422 and r.json()["detail"], (path, r.text)
        sid = client.post("/api/sessions", json={"performer": "Numbers"}).json()["id"]
        try:
            for query in ("since=9223372036854775808", "since=-1"):
                r = client.get(f"/api/sessions/{sid}/events?{query}")
                assert r.status_code == 422, (query, r.text)
            for since in ("1e400", "nan", "inf", "-inf"):
                r = client.get(f"/api/sessions/{sid}/residuals?since={since}")
                assert r.status_code == 422, (since, r.text)
        finally:
            client.post(f"/api/sessions/{sid}/stop")
        # A 30,000-level nested skeleton upload: refused, and the same keep-alive connection still serves.
        r = client.post("/api/skeletons?name=deep", content=b"[" * 30000 + b"]" * 30000,
                        headers={"content-type": "application/json"})
        assert r.status_code in (400, 413) and "nested" in r.json()["detail"] or r.status_code == 413, r.text
        r = client.post("/api/skeletons?name=deep", content=b'{"a":' * 2000 + b"1" + b"}" * 2000)
        assert r.status_code == 400 and "nested too deeply" in r.json()["detail"], r.text
        assert client.get("/api/status").status_code == 200


# --- 8. failed tokens back off ----------------------------------------------------------------------------
def test_repeated_wrong_tokens_make_the_address_wait(tmp_path):
    # docs/service.md: after 10 unrecognised tokens an address waits 1 s, doubling with each further failure.
    # The back-off runs on a clock the test moves (the service's own clock, handed to it, server/backoff.py):
    # the checks land inside the wait however slowly a loaded machine answers, and the wait ends when the
    # test has moved the clock past it, not a moment before.
    from flockcal.clock import ManualClock
    from flockcal.server.backoff import TokenBackoff

    settings = Settings(device=sim("backoff"), birds=4, http_port=free_port(), data_dir=tmp_path, token=ADMIN)
    with ServerThread(settings) as srv:
        wait_connected(srv.url, token=ADMIN)
        clock = ManualClock()
        srv.app.state.token_backoff = TokenBackoff(clock)
        url = srv.url + "/api/status"

        def status(token: str) -> httpx.Response:
            return httpx.get(url, headers={"Authorization": f"Bearer {token}"})

        async def socket_attempt():
            async with websockets.connect(srv.url.replace("http://", "ws://") + f"/ws/live?token={ADMIN}") as ws:
                return json.loads(await ws.recv())

        codes = [status(f"guess-{k:06d}").status_code for k in range(10)]
        assert codes == [401] * 10  # the first guesses are merely refused
        for failures in (11, 12, 13):
            assert status(f"guess-x{failures}").status_code == 401
            wait_s = 2.0 ** (failures - 11)
            # Now the address waits: a guess, and even the right token, get 429 with the time to wait, and
            # the websocket answers the same way (a token in the URL is checked through the same back-off).
            guess, right, first = status("guess-again"), status(ADMIN), asyncio.run(socket_attempt())
            assert guess.status_code == right.status_code == 429, (guess.text, right.text)
            assert int(guess.headers["retry-after"]) >= wait_s and "wait" in guess.json()["detail"]
            assert first["type"] == "error" and "wait" in first["message"], first
            # Still waiting a moment before the wait ends (a guess while waiting is not counted) ...
            clock.advance(wait_s - 0.01)
            assert status(ADMIN).status_code == 429
            # ... and let in once it has.
            clock.advance(0.02)
            assert status(ADMIN).status_code == 200


# --- 9. names, messages, documented figures ---------------------------------------------------------------
def test_names_are_matched_whole_and_invisible_characters_are_refused(open_server):
    srv = open_server
    before = sessions(srv)
    # A trailing newline used to pass the id and name checks ($ matches before a final newline).
    r = httpx.get(srv.url + "/api/sessions/20200101-000000-abcdef%0A")
    assert r.status_code == 400 and "not a session id" in r.json()["detail"], r.text
    assert httpx.get(srv.url + "/api/skeletons/Ann%0A").status_code == 400
    # Performer names that would reorder or break the text where they are shown.
    # (Inside the name: leading and trailing whitespace, U+2028 and U+0085 among it, is stripped.)
    for name in ("Ann\u202eevil", "An\u2028n", "An\u0085n", "\ufeffAnn", "Ann\u2066x"):
        r = httpx.post(srv.url + "/api/sessions", json={"performer": name})
        assert r.status_code == 422 and "performer name is" in r.json()["detail"], (name, r.text)
    assert sessions(srv) == before
    # A bad query value is told its own rule, not the sensor and performer rules.
    r = httpx.get(srv.url + "/api/sessions/20200101-000000-abcdef/bvh?units=xx")
    detail = r.json()["detail"]
    assert r.status_code == 422 and "units" in detail and "'xx'" in detail and "performer" not in detail, detail


def test_a_skeleton_file_naming_a_bad_performer_is_refused(open_server):
    srv = open_server
    sid = httpx.post(srv.url + "/api/sessions", json={"performer": "Sam"}).json()["id"]
    # 3 s of the tracker's frames (at 144 Hz), counted.
    wait_for(lambda: httpx.get(srv.url + f"/api/sessions/{sid}").json()["frames"] >= 432, 60, "432 frames")
    httpx.post(srv.url + f"/api/sessions/{sid}/stop", timeout=30)
    skeleton = httpx.get(srv.url + f"/api/sessions/{sid}/skeleton", timeout=30).json()
    listed = httpx.get(srv.url + "/api/skeletons").json()
    for where in ("source", "top"):
        bad = json.loads(json.dumps(skeleton))
        if where == "source":
            bad["source"]["performer"] = "<img src=x onerror=alert(1)>"
        else:
            bad["performer"] = "Sam\u202e"
        r = httpx.post(srv.url + "/api/skeletons?name=Sam", content=json.dumps(bad).encode())
        assert r.status_code == 400 and "performer" in r.json()["detail"], r.text
    assert httpx.get(srv.url + "/api/skeletons").json() == listed
    # The file as downloaded is fine.
    assert httpx.post(srv.url + "/api/skeletons?name=Sam", content=json.dumps(skeleton).encode()).status_code == 201


def test_the_documented_send_buffer_is_what_the_kernel_gives(open_server):
    import re
    from pathlib import Path

    from flockcal.server.listen import listen_socket

    text = (Path(__file__).parents[1] / "docs" / "websocket.md").read_text()
    asked, given = (int(x) * 1024 for x in re.search(r"send buffer is set to (\d+) kB, which Linux doubles to (\d+) kB",
                                                        text).groups())
    assert asked == Settings().send_buffer_bytes
    listener = listen_socket("127.0.0.1", 0, Settings().send_buffer_bytes)
    client = socket.create_connection(listener.getsockname())
    conn, _ = listener.accept()
    try:
        assert conn.getsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF) == given
    finally:
        for s in (conn, client, listener):
            s.close()


def test_the_documented_token_examples_are_accepted():
    import re
    import shlex
    from pathlib import Path

    from flockcal.cli import build_parser
    from flockcal.commands.serve import settings_from_args

    text = (Path(__file__).parents[1] / "docs" / "service.md").read_text()  # the serving example lives there
    line = re.search(r"^flockcal serve --host 0\.0\.0\.0 --token .*$", text, re.M).group(0)
    settings = settings_from_args(build_parser().parse_args(shlex.split(line)[1:])).check()
    assert settings.token and settings.read_token and settings.kiosk_token


# --- 8. pages that say there is more ------------------------------------------------------------------
def test_residuals_and_events_come_in_pages_that_say_there_is_more(open_server):
    srv = open_server
    sid = httpx.post(srv.url + "/api/sessions", json={"performer": "Pages"}).json()["id"]
    base = srv.url + f"/api/sessions/{sid}"
    # The series starts with the first fit: wait (by the session's clock, not the wall's) until it holds a
    # second of samples after its first, and the session 2.5 s.
    def a_second_of_samples() -> bool:
        series = httpx.get(base + "/residuals").json()["times"]
        return bool(series and series[-1] - series[0] >= 1.0
                    and httpx.get(srv.url + "/api/status").json()["session"]["time_s"] >= 2.5)

    wait_for(a_second_of_samples, 60.0, "a second of residual samples and 2.5 s of session")
    httpx.post(srv.url + f"/api/sessions/{sid}/stop", timeout=30)
    whole = httpx.get(base + "/residuals").json()
    times = whole["times"]
    assert not whole["more"] and len(times) >= 20
    # 20 samples a second of session time (docs/server.md), however the service's hand-overs fell: one per
    # 50 ms boundary the recorded frames crossed (a starved reader leaves gaps in their times), counted here
    # from the take's frame times; 2 spare for where the two clocks start. (One sample per hand-over gave 19
    # in 2.1 s with 0.58 s gaps at a load of 15, ~16 a second on a quiet machine.)
    with np.load(io.BytesIO(httpx.get(base + "/take", timeout=60).content)) as take:
        frame_times = take["times"]
    reached = np.floor(frame_times[(frame_times > times[0]) & (frame_times <= times[-1])] / 0.05)
    assert len(times) >= len(np.unique(reached)) - 2, (len(times), len(np.unique(reached)), times)
    assert np.all(np.diff(times) > 0), times  # one sample per instant: paging by time needs it
    # Pages of 7, followed by next_since, give every sample exactly once, the newest included.
    times, since = [], None
    while True:
        page = httpx.get(base + "/residuals", params={"limit": 7, **({"since": since} if since is not None else {})}).json()
        times += page["times"]
        if not page["more"]:
            break
        assert len(page["times"]) == 7
        since = page["next_since"]
    assert times == whole["times"]
    # Events the same way (a session has at least its started and stopped events).
    events = httpx.get(base + "/events").json()
    assert not events["more"] and len(events["events"]) >= 2
    first = httpx.get(base + "/events", params={"limit": 1}).json()
    assert first["more"] and first["events"] == events["events"][:1]
    rest = httpx.get(base + "/events", params={"since": first["next_since"], "limit": 5000}).json()
    assert first["events"] + rest["events"] == events["events"] and not rest["more"]
    # The service-wide list says where the next page is in a Link header.
    r = httpx.get(srv.url + "/api/events", params={"limit": 1})
    assert r.headers["link"].startswith(f'</api/events?since={r.json()[0]["id"]}&limit=1>')
    last = httpx.get(srv.url + "/api/events", params={"limit": 5000})
    assert "link" not in last.headers
