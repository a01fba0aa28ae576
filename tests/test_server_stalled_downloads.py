"""Downloads whose clients stopped reading (issue #37): a real `flockcal serve` in a child process on loopback
(tests/service_process.py) and raw sockets that stall a glTF or raw download; their slots come back, they are
cut off at the deadline, and a request sent meanwhile is answered whole. Waits are on conditions.
"""

from __future__ import annotations

import io
import socket
import time
from pathlib import Path

import h11
import httpx
import numpy as np

from break_probes import closed_by_peer, sim6
from server_helpers import free_port
from service_process import Serve, wait_for

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
            def answered():
                r = httpx.get(srv.url + path, timeout=120)
                assert r.status_code == 200 or "retry-after" in r.headers, r.headers
                return r if r.status_code != 503 else None

            # Tried again every half second (within the Retry-After the service asks for), as a client backs off.
            r = wait_for(answered, 43, "a slot came free", every=0.5)
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
