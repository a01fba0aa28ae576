"""A disk that fills while a session records, and a start on a full disk (issue #37), as an operator meets it:
`flockcal serve --min-free-mb 1` with its data directory on a real 32 MB filesystem (a tmpfs mounted for the
test), filled to the last byte by another process, then given room again.

Where no filesystem can be mounted (not root, no CAP_SYS_ADMIN), the same promises are checked with an
injected ENOSPC instead (`test_the_live_path_outlives_an_injected_enospc`): the service in this process, its
frame log's writes and its free-space look failing on purpose, its database capped with SQLite's own
`max_page_count`. Each test says which it is.
"""

from __future__ import annotations

import errno
import io
import json
import os
import subprocess
import threading
from contextlib import contextmanager
from pathlib import Path

import httpx
import numpy as np
import pytest
from websockets.sync.client import connect

from server_helpers import ServerThread, free_port, wait_connected
from service_process import Serve, run_serve, wait_for

SIM = ["--device", "sim://full?birds=6&motion=exercise&rate=100", "--birds", "6"]


def can_mount() -> bool:
    return os.geteuid() == 0 and not os.environ.get("FLOCKCAL_TEST_INJECT_ENOSPC")


@contextmanager
def small_filesystem(path: Path, mb: int):
    """A real `mb` MB filesystem at `path` (tmpfs), unmounted on the way out; skip when it cannot be mounted."""
    path.mkdir(parents=True, exist_ok=True)
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={mb}m", "tmpfs", str(path)],
                          capture_output=True, text=True, timeout=30)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({done.stderr.strip()}); the injected-ENOSPC test covers it")
    try:
        yield path
    finally:
        subprocess.run(["umount", "-l", str(path)], capture_output=True, timeout=30)


def fill(path: Path) -> Path:
    """What another process does: write a file until the disk refuses another byte."""
    filler = path / "filler"
    with open(filler, "wb", buffering=0) as fh:
        block = b"\0" * 65536
        while block:
            try:
                fh.write(block)
            except OSError as exc:
                assert exc.errno == errno.ENOSPC, exc
                block = block[: len(block) // 2]
    return filler


class Listener:
    """A websocket client (status, events, pose) reading on a thread of its own; `messages` as they came."""

    def __init__(self, url: str):
        self._client = connect(url.replace("http://", "ws://") + "/ws/live", open_timeout=30)
        self.ws = self._client.__enter__()  # left in close()
        self.ws.recv(timeout=30)  # hello
        self.ws.send(json.dumps({"type": "subscribe", "rate_hz": 20, "content": ["status", "events", "pose"]}))
        self.messages: list[dict] = []
        self.thread = threading.Thread(target=self._read, daemon=True)
        self.thread.start()

    def _read(self) -> None:
        try:
            for text in self.ws:
                self.messages.append(json.loads(text))
        except Exception:  # closed at the end of the test
            pass

    def events(self, action: str) -> list[dict]:
        return [m["event"] for m in list(self.messages) if m["type"] == "event" and m["event"].get("action") == action]

    def count(self, kind: str) -> int:
        return sum(m["type"] == kind for m in list(self.messages))

    def close(self) -> None:
        self._client.__exit__(None, None, None)
        self.thread.join(10)


def status(url: str) -> dict:
    return httpx.get(url + "/api/status", timeout=10).json()


def frames_of(url: str, sid: str) -> int:
    return httpx.get(url + f"/api/sessions/{sid}", timeout=10).json()["frames"]


def whole_records(recording: Path) -> int:
    """Whole frames in a frame log as another process sees it on disk (its reader counts the whole blocks)."""
    from flockcal.server.framelog import FrameLogReader

    with FrameLogReader(recording) as log:
        return log.n


def check_the_full_disk(url: str, recordings: Path, fill_disk, give_room) -> None:
    """The promises, whatever makes the disk full: what an operator sees and can do."""
    old = httpx.post(url + "/api/sessions", json={"performer": "Old"}).json()["id"]
    wait_for(lambda: frames_of(url, old) >= 100, 60.0, "the old session's frames")
    assert httpx.post(url + f"/api/sessions/{old}/stop", timeout=60).status_code == 200
    sid = httpx.post(url + "/api/sessions", json={"performer": "Ann"}).json()["id"]
    wait_for(lambda: frames_of(url, sid) >= 200, 60.0, "Ann's frames")
    listener = Listener(url)
    try:
        # What was written before the disk filled is kept; frames still in the log's buffer (flushed a few
        # times a second) had no room to go to.
        written = whole_records(recordings / f"{sid}.frames")
        assert written > 0
        fill_disk()
        # Seen at once (deadlines: the disk is looked at once a second; 10 s for a loaded machine).
        full = wait_for(lambda: (st := status(url))["disk"]["full"] and st, 10.0, "/api/status saying the disk is full")
        assert "room" in full["disk"]["message"] or "free" in full["disk"]["message"], full["disk"]
        wait_for(lambda: listener.events("disk_full"), 10.0, "a disk_full event on the websocket")
        # Recording stops cleanly: the session is stopped, its row says why, its result is there.
        wait_for(lambda: status(url)["session"] is None, 30.0, "the session stopped")
        row = httpx.get(url + f"/api/sessions/{sid}").json()
        assert row["state"] == "stopped" and row["has_result"] and "stopped" in (row["note"] or ""), row
        # The live path goes on: frames still counted, status and poses still sent.
        frames, poses = status(url)["frames"], listener.count("pose")
        wait_for(lambda: status(url)["frames"] >= frames + 100, 20.0, "frames still read while the disk is full")
        wait_for(lambda: listener.count("pose") >= poses + 10, 20.0, "poses still sent while the disk is full")
        # What was written is kept and readable.
        r = httpx.get(url + f"/api/sessions/{sid}/take", timeout=60)
        assert r.status_code == 200
        with np.load(io.BytesIO(r.content)) as take:
            assert written <= take["times"].shape[0] <= row["frames"], (written, take["times"].shape, row["frames"])
            assert np.isfinite(take["positions"]).all()
        # No session starts meanwhile; deleting an old one works or says 507.
        r = httpx.post(url + "/api/sessions", json={"performer": "Bo"}, timeout=30)
        assert r.status_code == 507 and r.json()["detail"], r.text
        r = httpx.delete(url + f"/api/sessions/{old}", timeout=30)
        assert r.status_code in (204, 507), r.text

        give_room()
        wait_for(lambda: not status(url)["disk"]["full"], 10.0, "the disk no longer full")
        wait_for(lambda: listener.events("disk_ok"), 10.0, "a disk_ok event on the websocket")
    finally:
        listener.close()
    # What was held in memory is in the database now.
    actions = [e.get("action") for e in httpx.get(url + "/api/events?limit=5000").json()]
    assert "disk_full" in actions and "disk_ok" in actions, actions
    limit = [e for e in httpx.get(url + f"/api/sessions/{sid}/events").json()["events"] if e.get("action") == "limit"]
    assert limit and limit[0]["reason"] == "disk_full", limit
    assert httpx.get(url + f"/api/sessions/{sid}").json()["state"] == "stopped"
    # And the next guest records.
    r = httpx.post(url + "/api/sessions", json={"performer": "Cy"}, timeout=30)
    assert r.status_code == 201, r.text
    nxt = r.json()["id"]
    wait_for(lambda: frames_of(url, nxt) >= 100, 60.0, "the next session's frames")
    r = httpx.post(url + f"/api/sessions/{nxt}/stop", timeout=60)
    assert r.status_code == 200 and r.json()["has_result"], r.text


@pytest.mark.skipif(not can_mount(), reason="mounting a tmpfs needs root; the injected-ENOSPC test runs instead")
def test_a_disk_that_fills_while_a_session_records_stops_only_the_recording(tmp_path):
    """Real filesystem: a 32 MB tmpfs, filled by this test (another process to the service)."""
    with small_filesystem(tmp_path / "fs", 32) as fs:
        data = fs / "data"
        with Serve(SIM + ["--data-dir", data, "--min-free-mb", "1"], free_port(), tmp_path / "serve.log") as srv:
            holder = {}

            def fill_disk():
                holder["filler"] = fill(fs)

            check_the_full_disk(srv.url, data / "recordings", fill_disk, lambda: holder["filler"].unlink())
            assert srv.stop() in (0, 130)  # Ctrl-C: 0 or 130 by uvicorn version (docs/cli.md)
        out = srv.output()
    assert "Traceback" not in out, out[-3000:]


@pytest.mark.skipif(not can_mount(), reason="mounting a tmpfs needs root")
def test_a_start_on_a_full_disk_is_one_line_naming_the_path(tmp_path):
    """Real filesystem: `serve` with its data directory on a full 4 MB tmpfs, new and already used (a
    traceback and exit 1 before)."""
    with small_filesystem(tmp_path / "fs", 4) as fs:
        used = fs / "used"
        with Serve(SIM + ["--data-dir", used, "--min-free-mb", "0"], free_port(), tmp_path / "serve.log") as srv:
            assert srv.stop() in (0, 130)  # Ctrl-C: 0 or 130 by uvicorn version (docs/cli.md)
        fill(fs)
        for data in (fs / "new", used):
            out = run_serve(SIM + ["--data-dir", data])
            line = out.stderr.strip()
            assert out.returncode == 2 and "\n" not in line and "Traceback" not in line, out.stderr
            assert str(data) in line and ("full" in line or "No space" in line), line


@pytest.mark.skipif(can_mount(), reason="a real filesystem is mounted instead (the test above)")
def test_the_live_path_outlives_an_injected_enospc(tmp_path, monkeypatch):
    """Injected ENOSPC, for machines that cannot mount a filesystem: the service runs in this process; once
    'full', its frame log's writes raise ENOSPC, its free-space look says 0 bytes, and its database may not grow
    (SQLite's max_page_count at the current size), until room is given back."""
    import flockcal.server.framelog as framelog
    import flockcal.server.limits as limits
    from flockcal.server.settings import Settings

    full = threading.Event()
    write_all, free_bytes = framelog._write_all, limits.free_bytes

    def failing_write(fd, data):
        if full.is_set():
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        write_all(fd, data)

    monkeypatch.setattr(framelog, "_write_all", failing_write)
    monkeypatch.setattr(limits, "free_bytes", lambda path: 0 if full.is_set() else free_bytes(path))
    settings = Settings(device="sim://injected?birds=6&motion=exercise&rate=100", birds=6, http_port=free_port(),
                        data_dir=tmp_path / "data", min_free_bytes=2**20)
    with ServerThread(settings) as srv:
        wait_connected(srv.url)
        db = srv.service.store

        def fill_disk():
            with db._lock:
                pages = db._db.execute("PRAGMA page_count").fetchone()[0]
                db._db.execute(f"PRAGMA max_page_count = {pages}")
            full.set()

        def give_room():
            with db._lock:
                db._db.execute("PRAGMA max_page_count = 1073741823")
            full.clear()

        check_the_full_disk(srv.url, settings.data_dir / "recordings", fill_disk, give_room)
