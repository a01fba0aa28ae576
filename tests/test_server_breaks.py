"""The service when things run out or break (issue #37), probed as a careless operator and an attacker do it:
a real `flockcal serve` in a child process on loopback (tests/service_process.py), raw sockets, websockets,
files damaged on disk. Each test says what was tried; waits are on conditions, with their deadlines stated.

A full disk has its own module (tests/test_server_disk_full.py).
"""

from __future__ import annotations

import asyncio
import base64
import io
import json
import os
import resource
import shutil
import signal
import socket
import sqlite3
import time
from pathlib import Path

import h11
import httpx
import numpy as np
import pytest
import websockets

from server_helpers import free_port
from service_process import Serve, run_serve, wait_for

GOLDEN_SKELETON = Path(__file__).parent / "golden" / "calibration" / "skeleton_file.json"


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


# --- descriptors ---------------------------------------------------------------------------------------
def test_a_thousand_half_sent_requests_cannot_keep_the_service_from_answering(tmp_path):
    """What was tried (the issue's attack): the open-files limit a unit without LimitNOFILE gets (soft 1024),
    then 1,100 connections that each send half a request and wait. /api/status must answer within 5 s
    throughout, every attacking connection is closed by the service (a request deadline of 2 s, the option's
    default being 10; allowed: 2 s + 30 s of margin for a loaded machine), and the log grows by less than
    1 MB."""
    attackers = 1100
    own_open_files(attackers + 200)
    hard = resource.getrlimit(resource.RLIMIT_NOFILE)[1]
    with Serve(sim6("fds") + ["--request-deadline-s", "2"], free_port(), tmp_path / "serve.log",
               nofile=(1024, hard)) as srv:
        limits = Path(f"/proc/{srv.proc.pid}/limits").read_text()
        soft_now = next(line.split()[3] for line in limits.splitlines() if line.startswith("Max open files"))
        assert soft_now == ("unlimited" if hard == resource.RLIM_INFINITY else str(hard)), limits  # raised to hard
        log_before = srv.log.stat().st_size
        socks = []
        try:
            for _ in range(attackers):
                s = socket.create_connection(("127.0.0.1", srv.port), timeout=30)
                s.sendall(b"GET /api/status HTTP/1.1\r\nHost: 127.0.0.1\r\n")  # no blank line: never whole
                socks.append(s)
            probes = []
            deadline = time.monotonic() + 32.0
            while not all(closed_by_peer(s) for s in socks):
                assert time.monotonic() < deadline, \
                    f"{sum(not closed_by_peer(s) for s in socks)} half-sent requests still open after 32 s"
                start = time.monotonic()
                r = status_within(srv.url)
                probes.append(time.monotonic() - start)
                assert r.status_code == 200, r.text
                time.sleep(0.5)  # a probe every half second, as a dashboard polls; not a synchronisation
            assert status_within(srv.url).status_code == 200
            counts = status_within(srv.url).json()["connections"]
        finally:
            for s in socks:
                s.close()
        assert counts["timed_out"] + counts["evicted"] >= attackers - 5 and counts["request_deadline_s"] == 2, counts
        assert srv.proc.poll() is None
        growth = srv.log.stat().st_size - log_before
    assert growth < 2**20, f"the log grew by {growth} bytes"
    assert "Traceback" not in srv.output()
    print(f"probes: {len(probes)}, slowest {max(probes):.2f} s; log +{growth} bytes; {counts}")


def ws_handshake(port: int) -> tuple[socket.socket, bytes]:
    """A websocket handshake, then silence: (the socket, the reply's head). Once upgraded it is a busy
    connection (the service cannot close it for a newcomer), not one waiting for its request."""
    s = socket.create_connection(("127.0.0.1", port), timeout=30)
    key = base64.b64encode(os.urandom(16)).decode()
    s.sendall((f"GET /ws/live HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
               f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n").encode())
    head = b""
    while b"\r\n\r\n" not in head:
        part = s.recv(4096)
        if not part:
            break
        head += part
    return s, head


def test_when_connections_run_out_the_service_evicts_idle_ones_or_sheds_load_with_503(tmp_path):
    """What was tried: a service whose hard limit is 256 open files (so it keeps at most 64 connections), then
    (a) 150 half-sent requests: each newcomer closes the one waiting longest, and /api/status answers within 5 s;
    (b) 70 websockets holding every connection: a new request gets 503 with Retry-After at once, and once
    some of them leave, /api/status answers again."""
    with Serve(sim6("shed"), free_port(), tmp_path / "serve.log", nofile=(256, 256)) as srv:
        cap = status_within(srv.url).json()["connections"]["cap"]
        assert cap == 64
        half = []
        try:
            for _ in range(150):
                s = socket.create_connection(("127.0.0.1", srv.port), timeout=30)
                s.sendall(b"GET /api/status HTTP/1.1\r\n")
                half.append(s)
            assert status_within(srv.url).status_code == 200
            wait_for(lambda: sum(closed_by_peer(s) for s in half) >= 150 - cap, 30.0,
                     "the oldest half-sent requests closed for newcomers")
        finally:
            for s in half:
                s.close()
        busy = []
        try:
            wait_for(lambda: status_within(srv.url).json()["connections"]["http_open"] <= 2, 30.0,
                     "the half-sent requests gone")
            for _ in range(cap + 6):  # until one is turned away
                sock, head = ws_handshake(srv.port)
                if not head.startswith(b"HTTP/1.1 101"):
                    sock.close()
                    break
                busy.append(sock)
            assert cap - 4 <= len(busy) <= cap, len(busy)  # (a few descriptors are the service's own requests)
            assert head.startswith(b"HTTP/1.1 503") and b"retry-after: 5" in head.lower(), head[:200]
            r = status_within(srv.url)
            assert r.status_code == 503 and int(r.headers["retry-after"]) > 0, (r.status_code, r.headers)
            assert "connections" in r.json()["detail"]
        finally:
            for s in busy[:20]:
                s.close()
        try:
            r = wait_for(lambda: (x := status_within(srv.url)).status_code == 200 and x, 30.0,
                         "/api/status answering once connections were free")
            assert r.json()["connections"]["shed"] >= 1
        finally:
            for s in busy[20:]:
                s.close()
        assert srv.proc.poll() is None


# --- websocket -----------------------------------------------------------------------------------------
def test_text_frames_that_are_not_utf8_close_with_1007_and_write_at_most_a_line_per_connection(tmp_path):
    """What was tried: 20 websockets each sending 200 text frames of invalid UTF-8 (the issue: 200 frames wrote
    1,200 lines of tracebacks), and one sending a single such frame, which must be closed with 1007."""
    with Serve(sim6("utf8"), free_port(), tmp_path / "serve.log") as srv:
        ws_url = srv.url.replace("http://", "ws://") + "/ws/live"
        before = srv.output().count("\n")

        async def one_frame() -> int:
            async with websockets.connect(ws_url) as ws:
                await ws.recv()  # hello
                await ws.send(b"\xff\xfe{bad", text=True)
                with pytest.raises(websockets.ConnectionClosed) as closed:
                    async with asyncio.timeout(10):
                        while True:
                            await ws.recv()
                return closed.value.rcvd.code if closed.value.rcvd else None

        async def flood() -> None:
            async with websockets.connect(ws_url) as ws:
                await ws.recv()
                try:
                    for _ in range(200):
                        await ws.send(b"\xc3\x28 not utf-8", text=True)
                except websockets.ConnectionClosed:
                    pass

        assert asyncio.run(one_frame()) == 1007

        async def many():
            await asyncio.gather(*(flood() for _ in range(20)), return_exceptions=True)

        asyncio.run(many())
        assert status_within(srv.url).status_code == 200
        lines = srv.output().splitlines()[before:]
    assert "Traceback" not in "\n".join(lines)
    assert len([x for x in lines if "UTF-8" in x]) <= 21, lines[:10]


def test_rate_hz_has_bounds_and_a_new_subscription_paces_at_once(tmp_path):
    """What was tried: `rate_hz: 1e-300` (accepted before: the socket went silent for good) gets an error and
    the socket stays; a subscription at 0.1 Hz, then one at 10 Hz, must be paced at 10 Hz at once: 3 status
    messages (sent at most twice a second) within 5 s, where the 0.1 Hz wait alone is 10 s."""
    with Serve(sim6("rate"), free_port(), tmp_path / "serve.log") as srv:
        ws_url = srv.url.replace("http://", "ws://") + "/ws/live"

        async def probe():
            async with websockets.connect(ws_url) as ws:
                await ws.recv()  # hello
                for bad in (1e-300, 0.05, 1e9):
                    await ws.send(json.dumps({"type": "subscribe", "rate_hz": bad, "content": ["status"]}))
                    msg = json.loads(await asyncio.wait_for(ws.recv(), 10))
                    assert msg["type"] == "error" and "rate_hz must be a number from 0.1" in msg["message"], msg
                await ws.send(json.dumps({"type": "subscribe", "rate_hz": 0.1, "content": ["status"]}))
                assert json.loads(await asyncio.wait_for(ws.recv(), 10))["type"] == "subscribed"
                assert json.loads(await asyncio.wait_for(ws.recv(), 10))["type"] == "status"  # the first at once
                await ws.send(json.dumps({"type": "subscribe", "rate_hz": 10, "content": ["status"]}))
                assert json.loads(await asyncio.wait_for(ws.recv(), 10))["type"] == "subscribed"
                start, seen = time.monotonic(), 0
                async with asyncio.timeout(5.0):
                    while seen < 3:
                        seen += json.loads(await ws.recv())["type"] == "status"
                return time.monotonic() - start

        took = asyncio.run(probe())
        print(f"3 status messages {took:.2f} s after the resubscription")


# --- lax input -----------------------------------------------------------------------------------------
@pytest.mark.parametrize("how", ["twelve spaces", "empty", "spaces in the environment", "inner space"])
def test_a_blank_or_spaced_token_is_refused_in_one_line(how):
    """What was tried: `--token` of 12 spaces (accepted before), an empty one, the same through $FLOCKCAL_TOKEN,
    and a token with a space inside."""
    args, env = {"twelve spaces": (["--token", " " * 12], {}), "empty": (["--token", ""], {}),
                 "spaces in the environment": ([], {"FLOCKCAL_TOKEN": " " * 12}),
                 "inner space": (["--token", "admin token-123"], {})}[how]
    os.environ.update(env)
    try:
        out = run_serve(["--data-dir", "/nonexistent-never-created"] + args)
    finally:
        for k in env:
            os.environ.pop(k)
    assert out.returncode == 2, out
    line = out.stderr.strip()
    assert "\n" not in line and "Traceback" not in line, line
    assert "--token" in line and "blank" in line, line
    assert not Path("/nonexistent-never-created").exists()


def test_numbers_sent_as_strings_are_422_and_change_nothing(tmp_path):
    """What was tried: `"distance_m": "0.01"` (the slip happened before), a boolean, and a session whose
    performer is a number; each is a 422 naming the field, and no slip or session follows."""
    with Serve(sim6("strict"), free_port(), tmp_path / "serve.log") as srv:
        for body, field in (({"sensor": "l_forearm", "distance_m": "0.01"}, "distance_m"),
                            ({"sensor": "l_forearm", "distance_m": True}, "distance_m"),
                            ({"sensor": "l_forearm", "distance_m": [0.01]}, "distance_m")):
            r = httpx.post(srv.url + "/api/simulator/slip", json=body)
            assert r.status_code == 422 and field in r.json()["detail"], r.text
        r = httpx.post(srv.url + "/api/sessions", json={"performer": 42})
        assert r.status_code == 422 and "performer" in r.json()["detail"], r.text
        assert httpx.get(srv.url + "/api/sessions").json()["sessions"] == []
        assert not any(e["type"] == "slip" for e in httpx.get(srv.url + "/api/events").json())
        # The same request with a number is taken (an int is a number too).
        assert httpx.post(srv.url + "/api/simulator/slip", json={"sensor": "l_forearm", "distance_m": 0.01}).status_code == 200


# --- SIGTERM -------------------------------------------------------------------------------------------
def test_sigterm_stops_the_session_and_prints_the_report_ctrl_c_prints(tmp_path):
    """What was tried: what `systemctl stop` sends, SIGTERM, while a guest's session records: the same stop
    path as Ctrl-C, and the same report, and exit 0."""
    data = tmp_path / "data"
    srv = Serve(sim6("term") + ["--data-dir", data], free_port(), tmp_path / "serve.log")
    with srv:
        sid = httpx.post(srv.url + "/api/sessions", json={"performer": "guest"}).json()["id"]
        wait_for(lambda: httpx.get(srv.url + f"/api/sessions/{sid}").json()["frames"] >= 200, 60.0, "200 frames")
        code = srv.stop(signal.SIGTERM)
    out = srv.output()
    assert code == 0, out[-2000:]
    assert f"flockcal serve: stopped session {sid} (guest, " in out and "result stored" in out, out[-2000:]
    assert f"flockcal serve: saved {data / 'recordings' / (sid + '.frames')}" in out
    assert f"flockcal serve: sessions, results and events in {data / 'flockcal.sqlite3'}" in out
    with sqlite3.connect(data / "flockcal.sqlite3") as db:
        state, result = db.execute("SELECT state, result FROM sessions WHERE id = ?", (sid,)).fetchone()
    assert state == "stopped" and result is not None


# --- skeletons -----------------------------------------------------------------------------------------
def far_skeleton(tmp_path: Path) -> Path:
    data = json.loads(GOLDEN_SKELETON.read_text())
    data["joints"][0]["c"] = [1e200, 0.0, 0.0]
    path = tmp_path / "far.json"
    path.write_text(json.dumps(data))
    return path


def test_a_skeleton_metres_away_from_its_sensor_is_refused_everywhere_and_skipped_when_stored(tmp_path):
    """What was tried: a skeleton file whose first joint centre is [1e200, 0, 0] m — uploaded (a 500 before),
    given to `serve --skeleton` (a traceback), and lying in the data directory's skeletons/ (the service did not
    start: a restart loop under the unit)."""
    far = far_skeleton(tmp_path)
    out = run_serve(sim6("skelcli") + ["--data-dir", tmp_path / "cli", "--skeleton", far])
    assert out.returncode == 2 and "Traceback" not in out.stderr, out.stderr
    line = out.stderr.strip()
    assert "\n" not in line and str(far) in line and "from its sensor" in line, line

    data = tmp_path / "data"
    (data / "skeletons").mkdir(parents=True)
    stored = data / "skeletons" / "Far.json"
    shutil.copy(far, stored)
    with Serve(sim6("skelstore") + ["--data-dir", data], free_port(), tmp_path / "serve.log") as srv:
        assert "stored skeleton Far.json not loaded" in srv.output()
        assert httpx.get(srv.url + "/api/skeletons").json()["skeletons"] == []
        r = httpx.post(srv.url + "/api/skeletons?name=Far", content=far.read_bytes())
        assert r.status_code == 422 and "from its sensor" in r.json()["detail"], r.text
        good = httpx.post(srv.url + "/api/skeletons?name=Good", content=GOLDEN_SKELETON.read_bytes())
        assert good.status_code == 201, good.text
    assert stored.read_bytes() == far.read_bytes()  # left on disk, untouched


# --- downloads -----------------------------------------------------------------------------------------
def big_session(data: Path, frames: int = 100_000, moving: bool = False) -> str:
    """A stopped session of 4 sensors whose take is 40 MB (its frame log, deflated, far less), put in the data
    directory before the service starts (as retention's benchmark does): big enough that a client that stops
    reading stalls its download.
    `moving`: a chain a-b-c-d turning about ball joints (so a re-solve finds joints), else all at rest."""
    from flockcal.server.framelog import FrameLog
    from flockcal.server.store import Store

    sid = "20200101-000000-b16b16"
    names = ["a", "b", "c", "d"]
    (data / "recordings").mkdir(parents=True)
    log = FrameLog(data / "recordings" / f"{sid}.frames", names, 60.0)
    times = np.arange(frames) / 60.0
    if moving:
        rot, pos = turning_chain(times, 4)
    else:
        rot, pos = np.broadcast_to(np.eye(3), (frames, 4, 3, 3)), np.zeros((frames, 4, 3))
    log.write(times, rot, pos, np.ones((frames, 4), bool))
    log.close()
    store = Store(data / "flockcal.sqlite3")
    store.insert_session({"id": sid, "performer": "Big", "state": "stopped", "names": names, "device": "test",
                          "created_at": time.time(), "frames": frames})
    store.close()
    return sid


def turning_chain(times: np.ndarray, m: int) -> tuple[np.ndarray, np.ndarray]:
    """Rotations and positions of `m` bodies in a chain, each turning on its own sinusoids, each body's
    sensor 0.2 m from its joint with the next: the joint points agree in the world at every frame."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(7)
    n = len(times)
    freq = rng.uniform(0.1, 0.6, (m, 3))
    phase = rng.uniform(0, 2 * np.pi, (m, 3))
    rotvec = 0.9 * np.sin(2 * np.pi * freq[None] * times[:, None, None] + phase[None])
    rot = Rotation.from_rotvec(rotvec.reshape(-1, 3)).as_matrix().reshape(n, m, 3, 3)
    pos = np.zeros((n, m, 3))
    c, l = np.array([0.2, 0.0, 0.0]), np.array([-0.2, 0.0, 0.0])  # the joint in the parent's and child's frames
    for i in range(1, m):  # R_p c + t_p = R_i l + t_i
        pos[:, i] = rot[:, i - 1] @ c + pos[:, i - 1] - rot[:, i] @ l
    return rot, pos


def stalled_download(port: int, path: str) -> socket.socket:
    """Request a download and read nothing after its status line (a small receive buffer, so it stalls)."""
    s = socket.socket()
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    s.connect(("127.0.0.1", port))
    s.sendall(f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n".encode())
    assert s.recv(12).startswith(b"HTTP/1.1 200"), "the download did not start"
    return s


def test_downloads_whose_clients_stopped_reading_give_their_slots_back(tmp_path):
    """What was tried (the issue): 8 clients request a session's /take and stop reading; they held every slot for
    good, and the next client got 503 after 503 without Retry-After. Now the next client gets 503 with
    Retry-After, and has its whole file once the stalled ones are cut off (`--download-stall-s 3`, the
    default being 30: 3 s without a read; allowed: 3 s + 40 s of margin).

    The ninth must ask within those 3 s of the first client's stall: on a loaded machine (load 10-17) setting
    up the eight took longer, a stalled one had been cut off and the ninth got its slot. So a ninth let in
    counts only when /api/status says a download had been cut off by then (`downloads.stalled`: it is counted
    before the slot is freed); then the eight are opened again, at most 3 times."""
    data = tmp_path / "data"
    sid = big_session(data)
    with Serve(sim6("slots") + ["--data-dir", data, "--download-stall-s", "3"], free_port(),
               tmp_path / "serve.log") as srv:
        path = f"/api/sessions/{sid}/take"

        def downloads() -> dict:
            return httpx.get(srv.url + "/api/status", timeout=30).json()["downloads"]

        opened: list[socket.socket] = []
        try:
            for attempt in range(3):
                held = [stalled_download(srv.port, path) for _ in range(8)]
                opened += held
                with httpx.stream("GET", srv.url + path, timeout=30) as first:
                    if first.status_code == 503:
                        first.read()  # its detail, checked below
                    else:  # read as its answer starts: a whole take lasts long enough for the eight to stall
                        stalled = downloads()["stalled"]
                if first.status_code == 503:
                    break
                assert first.status_code == 200, first.status_code
                assert stalled > 0, "a ninth download got a slot while eight held theirs"
                for s in held:
                    s.close()
                wait_for(lambda: downloads()["running"] == 0, 30, "closed downloads did not give their slots back")
            else:
                raise AssertionError("3 times, a stalled download was cut off before the ninth had its answer")
            assert int(first.headers["retry-after"]) > 0 and "3 s" in first.json()["detail"]
            start = time.monotonic()
            while (r := httpx.get(srv.url + path, timeout=120)).status_code == 503:
                assert "retry-after" in r.headers
                assert time.monotonic() - start < 43, "no slot came free within 43 s"
                time.sleep(min(float(r.headers["retry-after"]), 0.5))  # the client's back-off, not a sync
            assert r.status_code == 200
            with np.load(io.BytesIO(r.content)) as take:
                assert take["positions"].shape == (100_000, 4, 3)
            assert all(closed_by_peer(s) for s in held), "a stalled client's connection is still open"
            status = httpx.get(srv.url + "/api/status").json()
            assert status["connections"]["http_open"] <= 2
            assert status["downloads"]["stalled"] >= 8 and status["downloads"]["running"] == 0, status["downloads"]
        finally:
            for s in opened:
                s.close()


def test_a_stalled_gltf_download_is_cut_off_and_its_slot_freed(tmp_path):
    """What was tried: a client asks for a long session's /gltf (the rig with 100,000 frames of animation) and
    reads nothing after the status line. The download held its slot for good (it streamed without the stall
    clock /take and /bvh have). Now it is cut off after `--download-stall-s 3` (allowed: 3 s + 40 s of
    margin): /api/status counts it stalled, its slot comes back, the connection is closed, and the next
    client has the whole .glb."""
    data = tmp_path / "data"
    sid = big_session(data, moving=True)
    with Serve(sim6("gltf-stall") + ["--data-dir", data, "--download-stall-s", "3"], free_port(),
               tmp_path / "serve.log") as srv:
        path = f"/api/sessions/{sid}/gltf"
        solved = httpx.post(srv.url + f"/api/sessions/{sid}/resolve", timeout=300)
        assert solved.status_code == 200, solved.text

        def downloads() -> dict:
            return httpx.get(srv.url + "/api/status", timeout=30).json()["downloads"]

        s = stalled_download(srv.port, path)
        try:
            wait_for(lambda: downloads()["stalled"] == 1, 43, "the stalled /gltf download was never cut off")
            wait_for(lambda: downloads()["running"] == 0, 30, "the cut-off download kept its slot")
            wait_for(lambda: closed_by_peer(s), 30, "the stalled client's connection is still open")
        finally:
            s.close()
        whole = httpx.get(srv.url + path, timeout=120)
        assert whole.status_code == 200, whole.text[:200]
        assert whole.content[:4] == b"glTF" and int.from_bytes(whole.content[8:12], "little") == len(whole.content)


def test_a_stalled_raw_download_is_cut_off(tmp_path):
    """What was tried: a client asks for a stopped session's raw recording (40 MB, sent as the file it is)
    and reads nothing after the status line. It held its connection and the open file for good (a file takes
    no download slot, and had no stall clock). Now it is cut off after `--download-stall-s 3` (allowed: 3 s +
    40 s of margin): /api/status counts it stalled, no slot was taken, the connection is closed, and the
    next client has the whole file, byte for byte."""
    data = tmp_path / "data"
    sid = big_session(data, frames=1000)
    raw = np.random.default_rng(3).integers(0, 256, 40_000_000, dtype=np.uint8).tobytes()
    (data / "recordings" / f"{sid}.fobraw").write_bytes(raw)
    with Serve(sim6("raw-stall") + ["--data-dir", data, "--download-stall-s", "3"], free_port(),
               tmp_path / "serve.log") as srv:
        path = f"/api/sessions/{sid}/raw"

        def downloads() -> dict:
            return httpx.get(srv.url + "/api/status", timeout=30).json()["downloads"]

        s = stalled_download(srv.port, path)
        try:
            assert downloads()["running"] == 0, "a raw download took a download slot"
            wait_for(lambda: downloads()["stalled"] == 1, 43, "the stalled raw download was never cut off")
            wait_for(lambda: closed_by_peer(s), 30, "the stalled client's connection is still open")
        finally:
            s.close()
        whole = httpx.get(srv.url + path, timeout=120)
        assert whole.status_code == 200 and whole.content == raw
        part = httpx.get(srv.url + path, headers={"Range": "bytes=1000-1999"}, timeout=30)  # resuming still works
        assert part.status_code == 206 and part.content == raw[1000:2000]


def test_a_request_sent_while_a_download_goes_out_is_answered_whole_after_the_deadline(tmp_path):
    """What was tried: a client that sends its next request (a second take) while the first take is still
    going out, reads the first whole, pauses past the request deadline (1 s here), then reads the second.
    The deadline its bytes had started used to go off while the second answer was going out: the connection
    was closed mid-download. Both takes must arrive whole, equal."""
    data = tmp_path / "data"
    sid = big_session(data, frames=5000)  # a 2 MB take: far more than the two sockets' buffers hold
    with Serve(sim6("pipelined") + ["--data-dir", data, "--request-deadline-s", "1"], free_port(),
               tmp_path / "serve.log") as srv:
        path = f"/api/sessions/{sid}/take"
        client = h11.Connection(h11.CLIENT)
        sock = socket.socket()
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        sock.settimeout(60)
        sock.connect(("127.0.0.1", srv.port))

        def request() -> bytes:
            return client.send(h11.Request(method="GET", target=path, headers=[("Host", "127.0.0.1")])) + \
                client.send(h11.EndOfMessage())

        def event():
            while (ev := client.next_event()) is h11.NEED_DATA:
                client.receive_data(sock.recv(65536))  # b"" (closed by the service) ends in an h11 error
            return ev

        def body() -> bytes:
            parts = []
            while not isinstance(ev := event(), h11.EndOfMessage):
                parts.append(bytes(ev.data))
            return b"".join(parts)

        try:
            sock.sendall(request())
            first = event()
            assert isinstance(first, h11.Response) and first.status_code == 200, first
            second = f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n".encode()
            sock.sendall(second)  # the first answer has only begun: its rest waits on this client
            one = body()
            client.start_next_cycle()
            assert request() == second  # (h11 told what was sent; the bytes went above)
            time.sleep(2.5)  # the client's pause: the deadline (1 s) and 1.5 s of margin, not a synchronisation
            response = event()
            assert isinstance(response, h11.Response) and response.status_code == 200, response
            two = body()
        finally:
            sock.close()
        assert one == two and len(one) > 1_000_000
        with np.load(io.BytesIO(two)) as take:
            assert take["positions"].shape == (5000, 4, 3)
        assert "Traceback" not in srv.output()


# --- damaged recordings --------------------------------------------------------------------------------
def record_sessions(url: str, n: int) -> list[str]:
    ids = []
    for k in range(n):
        sid = httpx.post(url + "/api/sessions", json={"performer": f"guest{k}"}).json()["id"]
        wait_for(lambda: httpx.get(url + f"/api/sessions/{sid}").json()["frames"] >= 300, 60.0, "300 frames")
        assert httpx.post(url + f"/api/sessions/{sid}/stop", timeout=60).status_code == 200
        ids.append(sid)
    return ids


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> tuple[Path, list[str]]:
    """A data directory holding three sessions recorded and stopped by a real serve, and their ids: each test
    damages a copy of its own (recording them once keeps the module short)."""
    data = tmp_path_factory.mktemp("recorded") / "data"
    with Serve(sim6("recorded") + ["--data-dir", data], free_port(), data.parent / "serve.log") as srv:
        ids = record_sessions(srv.url, 3)
        assert srv.stop() in (0, 130)  # Ctrl-C: 0 or 130 by uvicorn version (docs/cli.md)
    return data, ids


def copy_of(recorded, tmp_path: Path) -> tuple[Path, list[str]]:
    data = tmp_path / "data"
    shutil.copytree(recorded[0], data)
    return data, list(recorded[1])


def test_damaged_recordings_answer_a_4xx_with_a_message_and_no_download_breaks_off(recorded, tmp_path):
    """What was tried: a `.frames` cut inside its header, a `.fobraw` cut to 10 bytes, and 20 kB of random bytes
    in the middle of a `.frames` (resolve answered 500 and /bvh broke off after its 200 before). Every call
    answers 2xx, 4xx or 503, never 500; a 200 is a whole file; a 4xx says what is wrong."""
    data, (cut_header, cut_raw, noisy) = copy_of(recorded, tmp_path)
    rec = data / "recordings"
    # Damaged before the service starts: its start must not mind them either.
    (rec / f"{cut_header}.frames").write_bytes((rec / f"{cut_header}.frames").read_bytes()[:40])
    (rec / f"{cut_raw}.fobraw").write_bytes((rec / f"{cut_raw}.fobraw").read_bytes()[:10])
    body = bytearray((rec / f"{noisy}.frames").read_bytes())
    mid = len(body) // 2
    body[mid:mid + 20_000] = np.random.default_rng(37).integers(0, 256, 20_000, dtype=np.uint8).tobytes()
    (rec / f"{noisy}.frames").write_bytes(bytes(body))
    with Serve(sim6("damrec") + ["--data-dir", data], free_port(), tmp_path / "serve.log") as srv:
        for sid in (cut_header, cut_raw, noisy):
            for method, what in (("POST", "resolve"), ("GET", "take"), ("GET", "bvh"), ("GET", "skeleton"),
                                 ("GET", "raw")):
                with httpx.stream(method, srv.url + f"/api/sessions/{sid}/{what}", timeout=120) as r:
                    content = r.read()  # raises if the body breaks off
                    assert r.status_code != 500 and r.status_code < 600, (sid, what, r.status_code, content[:300])
                    if r.status_code >= 400:
                        assert r.status_code in (409, 410, 503) and json.loads(content)["detail"], (sid, what)
                        continue
                if what == "take":
                    with np.load(io.BytesIO(content)) as take:
                        assert take["valid"].shape[0] == take["times"].shape[0] > 0
                        assert np.isfinite(take["positions"]).all() and (np.diff(take["times"]) >= 0).all()
                elif what == "bvh":
                    text = content.decode()
                    stated = int(text.split("Frames:")[1].split()[0])
                    motion = text.split("Frame Time:")[1].strip().splitlines()[1:]
                    assert len(motion) == stated and "nan" not in text.lower(), (sid, stated, len(motion))
        r = httpx.post(srv.url + f"/api/sessions/{cut_header}/resolve")
        assert r.status_code == 409 and "cannot be read" in r.json()["detail"] and f"{cut_header}.frames" in r.json()["detail"]
        # The random bytes cost only the frames they hit: the rest still fits.
        r = httpx.post(srv.url + f"/api/sessions/{noisy}/resolve", timeout=120)
        assert r.status_code == 200 and r.json()["has_result"], r.text
    assert "Traceback" not in srv.output()


# --- a damaged database --------------------------------------------------------------------------------
def test_a_database_of_random_bytes_stops_the_start_with_its_own_exit_status_and_is_kept(tmp_path):
    """What was tried: a flockcal.sqlite3 of random bytes (a traceback and exit 1 before, restarted every 5 s
    for ever by the unit): one line naming the file and what to do, exit 4, the file untouched."""
    data = tmp_path / "data"
    data.mkdir()
    db = data / "flockcal.sqlite3"
    junk = np.random.default_rng(1).integers(0, 256, 65536, dtype=np.uint8).tobytes()
    db.write_bytes(junk)
    out = run_serve(sim6("junkdb") + ["--data-dir", data])
    line = out.stderr.strip()
    assert out.returncode == 4 and "\n" not in line and "Traceback" not in line, out.stderr
    assert str(db) in line and "damaged" in line and "move the file aside" in line, line
    assert db.read_bytes() == junk


def pages_overwritten(db: Path, seed: int) -> None:
    """Overwrite every page but the first (the header) with random bytes, as a failing disk might."""
    raw = bytearray(db.read_bytes())
    page = int.from_bytes(raw[16:18], "big") or 65536
    rng = np.random.default_rng(seed)
    for start in range(page, len(raw), page):
        raw[start:start + page] = rng.integers(0, 256, min(page, len(raw) - start), dtype=np.uint8).tobytes()
    db.write_bytes(bytes(raw))


CALLS = [("GET", "/api/status"), ("GET", "/api/sessions"), ("GET", "/api/sessions/presets"), ("GET", "/api/events"),
         ("GET", "/api/stats"), ("GET", "/api/skeletons"), ("GET", "/api/sessions/{id}"),
         ("GET", "/api/sessions/{id}/progress"), ("GET", "/api/sessions/{id}/result"),
         ("GET", "/api/sessions/{id}/residuals"), ("GET", "/api/sessions/{id}/events"),
         ("GET", "/api/sessions/{id}/take"), ("GET", "/api/sessions/{id}/raw"), ("GET", "/api/sessions/{id}/skeleton"),
         ("GET", "/api/sessions/{id}/bvh"), ("POST", "/api/sessions/{id}/resolve"), ("POST", "/api/sessions/{id}/pin"),
         ("DELETE", "/api/sessions/{id}/pin"), ("POST", "/api/sessions/{id}/stop"), ("GET", "/api/sessions/{other}"),
         ("GET", "/api/sessions/{other}/result"), ("GET", "/api/sessions/{other}/events"),
         ("GET", "/api/sessions/{other}/progress"), ("POST", "/api/sessions"), ("POST", "/api/sessions/{new}/stop"),
         ("DELETE", "/api/sessions/{other}"), ("GET", "/")]


def call_everything(url: str, sid: str, other: str) -> list[tuple[str, str, int, str]]:
    """The 27 calls of the issue's probe; (method, path, status, detail) of each."""
    out, new = [], "none"
    for method, path in CALLS:
        path = path.format(id=sid, other=other, new=new)
        body = {"performer": "next"} if path == "/api/sessions" else None
        r = httpx.request(method, url + path, json=body, timeout=120)
        if path == "/api/sessions" and r.status_code == 201:
            new = r.json()["id"]
            wait_for(lambda: httpx.get(url + f"/api/sessions/{new}").json()["frames"] > 0, 60.0, "frames")
        detail = r.json().get("detail", "") if r.headers.get("content-type", "").startswith("application/json") \
            and r.status_code >= 400 else ""
        out.append((method, path, r.status_code, detail))
        if r.status_code == 503:
            assert int(r.headers["retry-after"]) > 0, (method, path)
    return out


def test_a_damaged_database_is_found_at_start_and_damage_found_later_answers_503_not_500(recorded, tmp_path):
    """What was tried: (a) a real database whose data pages were overwritten: the start refuses it (exit 4)
    instead of serving 20 of 27 calls as 500; (b) rows whose stored JSON was overwritten (a damage the file's
    own check cannot see): the service starts, and of the 27 calls none answers 500, those reading the rows
    answer 503 naming the database and what to do; (c) data pages overwritten while the service runs:
    none of the 27 calls answers 500."""
    data, (sid, other, _) = copy_of(recorded, tmp_path)
    db = data / "flockcal.sqlite3"
    good = db.read_bytes()

    pages_overwritten(db, seed=5)
    out = run_serve(sim6("dbdmg2") + ["--data-dir", data])
    assert out.returncode == 4 and str(db) in out.stderr and "Traceback" not in out.stderr, out.stderr

    db.write_bytes(good)
    with sqlite3.connect(db) as con:
        con.execute("UPDATE sessions SET result = '{\"sensors\": [', progress = 'not json' WHERE id = ?", (sid,))
        con.execute("UPDATE events SET payload = x'ff00ff' WHERE session_id = ?", (sid,))
    with Serve(sim6("dbdmg3") + ["--data-dir", data], free_port(), tmp_path / "serve2.log") as srv:
        calls = call_everything(srv.url, sid, other)
        assert not [c for c in calls if c[2] >= 500 and c[2] != 503], calls
        damaged = [c for c in calls if c[2] == 503]
        assert damaged and all("damaged" in c[3] and str(db) in c[3] for c in damaged), damaged
        assert dict(((m, p), s) for m, p, s, _ in calls)[("GET", f"/api/sessions/{other}/result")] == 200

        # (c) the file damaged under the running service.
        pages_overwritten(db, seed=6)
        later = call_everything(srv.url, other, sid)
        assert not [c for c in later if c[2] >= 500 and c[2] != 503], later
        assert srv.proc.poll() is None
    assert "Traceback" not in srv.output()
