"""Session downloads stream from the frame log a chunk at a time (server/downloads.py) and hold what
loading the whole take at once gives: the .npz take, the BVH, the glTF rig and the skeleton file.

A real uvicorn on loopback records a short session from the built-in simulator; the references are
built the way the service built them before it streamed (read_frames → make_take → exports). The
memory bound itself is measured by benchmarks/bench_downloads.py (RSS is no unit-test figure).
"""

from __future__ import annotations

import io
import json
import socket
import time

import httpx
import numpy as np
import pytest

from flockcal.exports.bvh import bvh_chunks, bvh_text
from flockcal.exports.gltf import glb_chunks, gltf_bytes
from flockcal.exports.skeleton import skeleton_dict
from flockcal.exports.trc import trc_chunks, trc_text
from flockcal.server.framelog import FrameLog, read_frames
from flockcal.server.settings import Settings
from server_helpers import ServerThread, SlowDownload, free_port, wait_connected
from service_process import wait_for
from flockcal.takes import make_take


def take_of(path) -> object:
    """The reference: the whole log in memory, as SessionManager.take made it."""
    header, frames = read_frames(path)
    times = frames.times - frames.times[0]
    n = len(times)
    rate = header.rate_hz or (n - 1) / times[-1]  # a log without a rate: its arrivals' mean rate
    return make_take(frames.rotations, frames.positions, list(header.names), rate, valid=frames.valid, times=times)


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    settings = Settings(device="sim://downloads?birds=4&model=linkage&motion=exercise&rate=60", birds=4,
                        http_port=free_port(), data_dir=tmp_path_factory.mktemp("dl"))
    with ServerThread(settings) as srv:
        wait_connected(srv.url)
        sid = httpx.post(srv.url + "/api/sessions", json={"performer": "Dee"}).json()["id"]
        # 4 s of the tracker's frames (at 60 Hz), counted.
        wait_for(lambda: httpx.get(srv.url + f"/api/sessions/{sid}").json()["frames"] >= 240, 60, "240 frames")
        assert httpx.post(srv.url + f"/api/sessions/{sid}/stop", timeout=30).status_code == 200
        yield srv, sid


def test_streamed_take_equals_the_whole_take(session):
    srv, sid = session
    r = httpx.get(srv.url + f"/api/sessions/{sid}/take", timeout=30)
    assert r.status_code == 200 and "content-length" not in r.headers  # streamed, not built in memory
    got = np.load(io.BytesIO(r.content))
    want = take_of(srv.service.sessions.frames_path(sid))
    assert got["rotations"].shape[0] > 100
    np.testing.assert_array_equal(got["rotations"], want.rotations)
    np.testing.assert_array_equal(got["positions"], want.positions)
    np.testing.assert_array_equal(got["valid"], want.valid)
    np.testing.assert_array_equal(got["times"], want.times)
    assert list(got["names"]) == list(want.names) and float(got["rate_hz"]) == want.rate_hz


def test_the_live_frame_log_holds_the_trackers_words_not_floats(session):
    """The session's log, recorded by the real reader from the simulator's bytes, is stored as the tracker's
    words (server/frameblocks.py): under a third of the 8 + 4 + 4 × 96 bytes a frame of 4 birds as floats."""
    from flockcal.server.framelog import FrameLogReader

    srv, sid = session
    path = srv.service.sessions.frames_path(sid)
    with FrameLogReader(path) as log:
        version, n = log.version, log.n
    body = path.stat().st_size - len(path.read_bytes().split(b"\n", 1)[0]) - 1
    assert version == 2 and n > 100
    assert body / n < (8 + 4 + 4 * 96) / 3, f"{body / n:.0f} bytes a frame"


def test_streamed_bvh_and_skeleton_equal_the_exports_of_the_whole_take(session):
    srv, sid = session
    result = httpx.get(srv.url + f"/api/sessions/{sid}/result").json()
    take = take_of(srv.service.sessions.frames_path(sid))
    r = httpx.get(srv.url + f"/api/sessions/{sid}/bvh?units=mm&up=%2Bz", timeout=60)
    assert r.status_code == 200
    want = bvh_text(result, take, units="mm", up="+z")
    got_lines, want_lines = r.text.splitlines(), want.splitlines()
    head = want_lines.index("MOTION") + 3
    assert got_lines[:head] == want_lines[:head]
    # Rows from chunked reconstruction: the same numbers to the file's 6 decimals (± one last digit).
    np.testing.assert_allclose(np.loadtxt(got_lines[head:]), np.loadtxt(want_lines[head:]), atol=2e-6)
    r = httpx.get(srv.url + f"/api/sessions/{sid}/skeleton")
    assert r.status_code == 200
    got = json.loads(r.content)
    want = json.loads(json.dumps(skeleton_dict(result, source=got["source"], take=take)))
    for key in ("sensors", "root", "parent", "bones", "placements", "bodies"):
        assert got[key] == want[key], key
    assert got["source"]["frames"] == len(take.times)


def same_numbers(got, want, where="") -> None:
    """JSON values equal, numbers to 1e-12 m: a chunked mean (a rigid sensor's offset) rounds differently."""
    if isinstance(want, dict):
        assert got.keys() == want.keys(), where
        for key in want:
            same_numbers(got[key], want[key], f"{where}.{key}")
    elif isinstance(want, list):
        assert len(got) == len(want), where
        for k, (a, b) in enumerate(zip(got, want)):
            same_numbers(a, b, f"{where}[{k}]")
    elif isinstance(want, float):
        assert got == pytest.approx(want, abs=1e-12), where
    else:
        assert got == want, where


def glb_parts(data: bytes) -> tuple[dict, bytes]:
    """(JSON, BIN) of a .glb, each file's own chunk lengths (glTF 2.0 §4.4)."""
    assert data[:4] == b"glTF" and int.from_bytes(data[8:12], "little") == len(data)
    size = int.from_bytes(data[12:16], "little")
    return json.loads(data[20:20 + size]), data[20 + size + 8:]


def same_glb(got: bytes, want: bytes) -> None:
    """Equal .glb files up to rounding: the JSON's numbers to 1e-12 (a chunked mean prints with other
    digits, so the JSON chunk's length may differ), the buffer's floats to 1e-6 (chunked rotations are
    the same numbers but may round in their last float32 bit)."""
    (got_doc, got_bin), (want_doc, want_bin) = glb_parts(got), glb_parts(want)
    same_numbers(got_doc, want_doc)
    assert len(got_bin) == len(want_bin)
    np.testing.assert_allclose(np.frombuffer(got_bin, "<f4"), np.frombuffer(want_bin, "<f4"), atol=1e-6, rtol=0)


def test_streamed_gltf_equals_the_export_of_the_whole_take(session):
    srv, sid = session
    result = httpx.get(srv.url + f"/api/sessions/{sid}/result").json()
    take = take_of(srv.service.sessions.frames_path(sid))
    r = httpx.get(srv.url + f"/api/sessions/{sid}/gltf?up=%2Bz", timeout=60)
    assert r.status_code == 200 and r.headers["content-type"] == "model/gltf-binary"
    assert "content-length" not in r.headers and r.content[:4] == b"glTF"
    same_glb(r.content, gltf_bytes(result, take, up="+z", name=sid))
    # A four-body linkage is no humanoid: the plain rig, and the header says why (the CLI's one line).
    assert r.headers["x-flockcal-vrm"].startswith("none: ")
    # Tried: an up axis the tracker cannot have: the BVH's answer, one line, before any byte.
    bad = httpx.get(srv.url + f"/api/sessions/{sid}/gltf?up=%2Bx", timeout=60)
    assert bad.status_code == 409 and "up must be one of" in bad.json()["detail"]


def test_streamed_trc_equals_the_export_of_the_whole_take(session):
    srv, sid = session
    result = httpx.get(srv.url + f"/api/sessions/{sid}/result").json()
    take = take_of(srv.service.sessions.frames_path(sid))
    r = httpx.get(srv.url + f"/api/sessions/{sid}/trc?up=%2Bz", timeout=60)
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/plain")
    assert "content-length" not in r.headers and r.headers["content-disposition"].endswith(f'{sid}.trc"')
    assert r.text == trc_text(result, take, up="+z", file_name=f"{sid}.trc")
    # Tried: an up axis the tracker cannot have: one line, before any byte.
    bad = httpx.get(srv.url + f"/api/sessions/{sid}/trc?up=%2Bx", timeout=60)
    assert bad.status_code == 409 and "up must be one of" in bad.json()["detail"]


def test_chunked_exports_hold_dropouts_and_rigid_sensors_like_the_whole_take(session, tmp_path, monkeypatch):
    """Chunks of 7 frames, sensors dropping out across chunk edges (one invalid for its first 20
    frames), and a sensor declared rigid on its parent: what a whole-take export does with each."""
    from flockcal.server import downloads

    srv, sid = session
    header, data = read_frames(srv.service.sessions.frames_path(sid))
    rng = np.random.default_rng(3)
    valid = data.valid & (rng.random(data.valid.shape) > 0.1)
    valid[:20, 1] = False
    path = tmp_path / "gappy.frames"
    log = FrameLog(path, list(header.names), header.rate_hz)
    log.write(data.times, data.rotations, data.positions, valid)
    log.close()
    monkeypatch.setattr(downloads, "CHUNK_BYTES", 7 * downloads.record_dtype(len(header.names)).itemsize)
    frames = downloads.FrameFile(path)
    take = take_of(path)

    got = np.load(io.BytesIO(b"".join(downloads.npz_stream(frames))))
    np.testing.assert_array_equal(got["rotations"], take.rotations)
    np.testing.assert_array_equal(got["valid"], take.valid)

    result = httpx.get(srv.url + f"/api/sessions/{sid}/result").json()
    # The last sensor as if it rode rigidly on its parent: its joint comes from the frames.
    leaf = result["sensors"][-1] if result["sensors"][-1] in result["parent"] else result["sensors"][0]
    rigid = dict(result, joints=[j for j in result["joints"] if j["child"] != leaf],
                 rigid_groups=[[leaf, result["parent"][leaf]]])
    for calibration in (result, rigid):
        # The exports' writers reading the log as the routes have them read it (server/routes/sessions.py).
        want = bvh_text(calibration, take)
        got = "".join(bvh_chunks(calibration, frames, chunk_frames=frames.play_frames))
        head = want.splitlines().index("MOTION") + 3
        assert got.splitlines()[:head] == want.splitlines()[:head]
        np.testing.assert_allclose(np.loadtxt(got.splitlines()[head:]), np.loadtxt(want.splitlines()[head:]),
                                   atol=2e-6)
        streamed = b"".join(glb_chunks(calibration, frames, chunk_frames=frames.play_frames))
        same_glb(streamed, gltf_bytes(calibration, take))
        # One writer, two sinks: the temporary file of a download and the memory of a file, byte for byte.
        assert streamed == gltf_bytes(calibration, frames, chunk_frames=frames.play_frames)
        assert "".join(trc_chunks(calibration, frames, chunk_frames=frames.play_frames)) == trc_text(calibration, take)


def held_download(base_url: str, path: str) -> tuple[socket.socket, int]:
    """A GET whose client reads the status line and then nothing more (server_helpers.SlowDownload): the rest
    of a 40 MB body stays with the server."""
    download = SlowDownload(base_url, path)
    return download.sock, download.status


def test_downloads_beyond_the_limit_get_503_until_one_ends(tmp_path):
    """Two downloads held open by clients that read nothing more (a 40 MB take stays in flight), a
    third refused with 503; once a client goes away its slot is free again."""
    settings = Settings(device="sim://dlslots?birds=4&model=linkage&motion=exercise&rate=60", birds=4,
                        http_port=free_port(), data_dir=tmp_path, max_downloads=2)
    with ServerThread(settings) as srv:
        wait_connected(srv.url)
        sid = "20200101-000000-aaaaaa"
        names = list(srv.service.pipeline.names)
        n, m = 100_000, len(names)  # 100,000 frames of 4 sensors: 40 MB of log
        log = FrameLog(srv.service.sessions.frames_path(sid), names, 60.0)
        rot = np.broadcast_to(np.eye(3), (n, m, 3, 3))
        log.write(np.arange(n) / 60.0, rot, np.zeros((n, m, 3)), np.ones((n, m), bool))
        log.close()
        srv.service.store.insert_session({"id": sid, "performer": "Big", "state": "stopped", "names": names,
                                          "device": "test", "created_at": time.time(), "frames": n})
        url = f"/api/sessions/{sid}/take"
        held = [held_download(srv.url, url) for _ in range(2)]
        try:
            assert [status for _, status in held] == [200, 200]
            r = httpx.get(srv.url + url)
            assert r.status_code == 503 and "at most 2" in r.json()["detail"], r.text
            held.pop()[0].close()
            # The slot freed by the close is taken by the next request once the server has seen it go.
            r = wait_for(lambda: (r := httpx.get(srv.url + url, timeout=60)).status_code != 503 and r, 10,
                         "a download slot free again", every=0.1)
            assert r.status_code == 200 and len(r.content) > n * m * 97  # the whole take
        finally:
            for sock, _ in held:
                sock.close()
