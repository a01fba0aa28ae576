"""DELETE (and retention) while a session is being downloaded (docs/service.md, "Downloads and DELETE"): a
download already started is sent whole, the DELETE meanwhile answers 409 with Retry-After, retention passes
the session by, and once the download has ended the DELETE goes through; a download of what was deleted
answers 404, never a 500 or a cut-off body.

A real uvicorn on loopback and the built-in simulator; each download kind (the .npz take, BVH, glTF, raw
recording, skeleton file, TRC) is read by a slow client (64 KB receive buffer: a 20 MB body stays with the server)
that has its response's head before the DELETE is sent.
"""

from __future__ import annotations

import io
import json
import threading
import time

import httpx
import numpy as np
import pytest

from flockcal.server.framelog import FrameLog, read_frames
from flockcal.server.retention import Policy
from flockcal.server.settings import Settings
from server_helpers import ServerThread, SlowDownload, free_port, wait_connected
from service_process import wait_for

REPEAT = 200  # the recorded session's frames repeated: ~20 MB of frame log, more than any socket buffers


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    settings = Settings(device="sim://deldl?birds=4&model=linkage&motion=exercise&rate=60", birds=4,
                        http_port=free_port(), data_dir=tmp_path_factory.mktemp("deldl"))
    with ServerThread(settings) as srv:
        wait_connected(srv.url)
        sid = httpx.post(srv.url + "/api/sessions", json={"performer": "Dee"}).json()["id"]
        wait_for(lambda: httpx.get(srv.url + f"/api/sessions/{sid}").json()["frames"] >= 120, 30, "frames")
        r = httpx.post(srv.url + f"/api/sessions/{sid}/stop", timeout=30)
        assert r.status_code == 200 and r.json()["has_result"], r.text
        assert httpx.post(srv.url + f"/api/sessions/{sid}/pin").status_code == 200  # the copies' source stays
        yield srv, sid


def big_session(srv, source: str, n: int) -> str:
    """A stopped session of the recorded one's frames repeated REPEAT times, its result and raw bytes too."""
    mgr, store = srv.service.sessions, srv.service.store
    sid = f"20200101-000000-{n:06x}"
    header, data = read_frames(mgr.frames_path(source))
    k = len(data)
    step = data.times[-1] - data.times[0] + 1 / 60
    times = (data.times[None, :] + step * np.arange(REPEAT)[:, None]).ravel()
    log = FrameLog(mgr.frames_path(sid), list(header.names), header.rate_hz)
    for part in range(REPEAT):
        log.write(times[part * k:(part + 1) * k], data.rotations, data.positions, data.valid)
    log.close()
    mgr.raw_path(sid).write_bytes(mgr.raw_path(source).read_bytes() * 40)
    row = store.session(source)
    store.insert_session({"id": sid, "performer": "Big", "state": "stopped", "names": row.names,
                          "device": "test", "created_at": time.time(), "frames": k * REPEAT, "rate_hz": row.rate_hz})
    store.update_session(sid, result=store.result(source))
    return sid


def whole(kind: str, body: bytes, srv, sid: str, frames: int, raw: bytes) -> None:
    """The body is the whole download of its kind."""
    if kind == "take":
        assert np.load(io.BytesIO(body))["rotations"].shape[0] == frames
    elif kind == "bvh":
        text = body.decode()
        assert f"Frames: {frames}" in text and len(text.split("MOTION", 1)[1].strip().splitlines()) == frames + 2
    elif kind == "gltf":
        assert body[:4] == b"glTF" and int.from_bytes(body[8:12], "little") == len(body)
    elif kind == "raw":
        assert body == raw
    elif kind == "trc":  # the header's NumFrames, and the last row numbered as the last frame
        lines = body.decode().splitlines()
        assert lines[2].split("\t")[2] == str(frames) and lines[-1].split("\t")[0] == str(frames)
    else:
        assert json.loads(body)["source"]["frames"] == frames


@pytest.mark.parametrize("kind", ["take", "bvh", "gltf", "trc", "raw", "skeleton"])
def test_a_download_started_before_the_delete_is_sent_whole_and_the_delete_waits_its_turn(server, kind):
    srv, recorded = server
    sid = big_session(srv, recorded, ["take", "bvh", "gltf", "trc", "raw", "skeleton"].index(kind))
    frames = httpx.get(srv.url + f"/api/sessions/{sid}").json()["frames"]
    raw = srv.service.sessions.raw_path(sid).read_bytes()
    # Tried: a slow client has the head of its download; then the session is deleted, and a retention pass
    # with a budget of one byte looks at it.
    download = SlowDownload(srv.url, f"/api/sessions/{sid}/{kind}")
    assert download.status == 200, download.headers
    r = httpx.delete(srv.url + f"/api/sessions/{sid}")
    if kind == "skeleton":
        # Built whole before its first byte: the delete finds nothing in progress (or the build, and waits).
        assert r.status_code in (204, 409), r.text
    else:
        assert r.status_code == 409, r.text
        assert "being downloaded" in r.json()["detail"] and int(r.headers["retry-after"]) > 0
        retention = srv.service.retention
        retention.policy = Policy(keep_bytes=1)
        try:
            assert sid not in {p["id"] for p in retention.prune_once()}
        finally:
            retention.policy = Policy()
        assert srv.service.sessions.frames_path(sid).exists()
    whole(kind, download.body(), srv, sid, frames, raw)
    # Once the download has ended, the delete goes through; what was deleted answers 404, never 500.
    wait_for(lambda: httpx.delete(srv.url + f"/api/sessions/{sid}").status_code in (204, 404), 30,
             "the DELETE after the download")
    assert not srv.service.sessions.frames_path(sid).exists()
    for other in ("take", "bvh", "gltf", "trc", "raw", "skeleton", "result"):
        r = httpx.get(srv.url + f"/api/sessions/{sid}/{other}")
        assert r.status_code == 404 and r.json()["error"] == "not_found", (other, r.text)


def test_downloads_racing_a_delete_are_whole_or_404_never_500(server):
    srv, recorded = server
    sid = big_session(srv, recorded, 99)
    frames = httpx.get(srv.url + f"/api/sessions/{sid}").json()["frames"]
    raw = srv.service.sessions.raw_path(sid).read_bytes()
    got: list[tuple[str, int, str]] = []
    go = threading.Event()

    def fetch(kind: str) -> None:
        go.wait()
        with httpx.Client(timeout=60) as client:
            try:
                r = client.get(srv.url + f"/api/sessions/{sid}/{kind}")
            except httpx.HTTPError as exc:  # a cut-off body
                got.append((kind, -1, repr(exc)))
                return
            if r.status_code == 200:
                try:
                    whole(kind, r.content, srv, sid, frames, raw)
                except Exception as exc:
                    got.append((kind, -2, repr(exc)))
                    return
            got.append((kind, r.status_code, r.text[:200] if r.status_code != 200 else ""))

    # Tried: eight downloads (two of each streamed kind) and a DELETE sent at the same moment.
    kinds = ["take", "bvh", "gltf", "trc", "skeleton"] * 2
    threads = [threading.Thread(target=fetch, args=(k,)) for k in kinds]
    for t in threads:
        t.start()
    go.set()
    deleted = wait_for(lambda: httpx.delete(srv.url + f"/api/sessions/{sid}").status_code in (204, 404), 60,
                       "the DELETE")
    for t in threads:
        t.join(120)
    assert deleted and len(got) == len(kinds)
    assert all(status in (200, 404) for _, status, _ in got), got
