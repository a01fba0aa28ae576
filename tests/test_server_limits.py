"""Recording limits (server/limits.py): a session stops cleanly at the maximum length, and before the
disk fills; both leave a stored result and an event saying why; no session starts on a full disk.

A real uvicorn on loopback with the built-in simulator. The disk reserve is tried on a disk of the service's
own (`flockcal serve` on a tmpfs in a mount namespace of its own), so the session's own recording crosses it
whatever else the machine writes; the full-at-start check on the real disk the data directory is on.
"""

from __future__ import annotations

import io
import os
import shutil
import subprocess

import httpx
import numpy as np
import pytest

from flockcal.server.settings import Settings
from server_helpers import ServerThread, free_port, wait_connected
from service_process import Serve, wait_for


def statvfs_free(path) -> int:
    st = os.statvfs(path)
    return st.f_bavail * st.f_frsize


def wait_stopped(url: str, sid: str, timeout: float) -> dict:
    def stopped():
        row = httpx.get(url + f"/api/sessions/{sid}").json()
        return row if row["state"] != "live" else None

    return wait_for(stopped, timeout, f"session {sid} stops")


def limit_events(url: str, sid: str) -> list[dict]:
    events = httpx.get(url + f"/api/sessions/{sid}/events").json()["events"]
    return [e for e in events if e.get("action") == "limit"]


def test_a_session_stops_at_the_maximum_length_with_its_result(tmp_path):
    settings = Settings(device="sim://maxlen?birds=4&model=linkage&motion=exercise&rate=60", birds=4,
                        http_port=free_port(), data_dir=tmp_path, max_session_s=2.0)
    with ServerThread(settings) as srv:
        wait_connected(srv.url)
        sid = httpx.post(srv.url + "/api/sessions", json={"performer": "Long"}).json()["id"]
        row = wait_stopped(srv.url, sid, 20)
        events = limit_events(srv.url, sid)
    assert row["state"] == "stopped" and row["has_result"], row
    assert "maximum length" in row["note"], row
    assert [e["reason"] for e in events] == ["max_length"] and "--max-session-min" in events[0]["message"]
    # Stopped at the limit: 2 s of frames at 60 Hz, plus what arrives while the stop runs (a final fit;
    # ~0.2 s here, up to 2 s allowed for a loaded 2-core CI machine).
    assert 2.0 * 60 <= row["frames"] <= (2.0 + 2.0) * 60, row["frames"]


def _private_disk() -> str | None:
    """Why a private file system cannot be mounted here (None: it can): `unshare -rm` (a user and mount
    namespace of its own, no privilege needed where the kernel allows user namespaces) and tmpfs."""
    if shutil.which("unshare") is None:
        return "no unshare (util-linux)"
    try:
        probe = subprocess.run(["unshare", "-rm", "sh", "-c", "mount -t tmpfs -o size=1m tmpfs /tmp"],
                               capture_output=True, text=True, timeout=20)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"unshare -rm failed: {exc}"
    return None if probe.returncode == 0 else f"unshare -rm cannot mount a tmpfs: {probe.stderr.strip()[:200]}"


DISK_MB = 32  # the private disk the service records on
RESERVE_MB = 30  # --min-free-mb: the service starts with under 0.2 MB of it used, so 1.8 MB of frames cross it


@pytest.mark.skipif(_private_disk() is not None, reason=f"a private disk is needed: {_private_disk()}")
def test_recording_stops_cleanly_before_the_disk_reserve_is_reached(tmp_path):
    # The service runs on a disk of its own: a 32 MB tmpfs mounted in a mount namespace made for it alone
    # (unshare -rm), so no other program's writes or deletes move its free space and the session's own
    # frames (16 birds at 144 Hz: ~0.45 MB/s with the raw recording) are what cross the reserve.
    disk = tmp_path / "disk"
    disk.mkdir()
    mount = 'mount -t tmpfs -o size="$1"m tmpfs "$2" && shift 2 && exec "$@"'
    port = free_port()
    serve = Serve(["--device", "sim://diskfull?birds=16&motion=exercise&rate=144&baud=921600", "--birds", 16,
                   "--data-dir", disk / "data", "--min-free-mb", RESERVE_MB],
                  port, tmp_path / "serve.log", prefix=["unshare", "-rm", "sh", "-c", mount, "sh", DISK_MB, disk])
    with serve:
        url = serve.url
        wait_connected(url)
        status = httpx.get(url + "/api/status").json()["disk"]
        assert status["full"] is False and status["free_bytes"] > RESERVE_MB * 2**20, status
        assert status["free_bytes"] <= DISK_MB * 2**20, status  # the service records on the private disk
        r = httpx.post(url + "/api/sessions", json={"performer": "Disk"})
        assert r.status_code == 201, r.text
        sid = r.json()["id"]
        row = wait_stopped(url, sid, 120)
        events = limit_events(url, sid)
        assert row["state"] == "stopped" and row["has_result"], row
        assert [e["reason"] for e in events] == ["disk_full"] and "--min-free-mb" in events[0]["message"]
        assert "disk" in row["note"]
        # Stopped at the reserve, before the disk filled: no write was refused (the stop names the reserve,
        # not a failed write), and most of the disk is still free.
        assert "below the" in events[0]["message"] and "a write failed" not in events[0]["message"], events
        after = httpx.get(url + "/api/status").json()["disk"]
        assert after["full"] is True and 0.5 * RESERVE_MB * 2**20 < after["free_bytes"] < RESERVE_MB * 2**20, after
        # The recording is whole: its take downloads and holds every frame the row counts.
        r = httpx.get(url + f"/api/sessions/{sid}/take", timeout=60)
        assert r.status_code == 200
        take = np.load(io.BytesIO(r.content))
        assert len(take["times"]) == row["frames"] > 144, (len(take["times"]), row["frames"])
        serve.stop()  # reaped (an interrupted serve exits 130)


def test_no_session_starts_when_the_disk_is_at_the_reserve(tmp_path):
    st = os.statvfs(tmp_path)
    whole_disk = st.f_blocks * st.f_frsize  # a reserve no free space can meet
    settings = Settings(device="sim://nodisk?birds=4&model=linkage&motion=exercise&rate=60", birds=4,
                        http_port=free_port(), data_dir=tmp_path, min_free_bytes=whole_disk)
    with ServerThread(settings) as srv:
        wait_connected(srv.url)
        r = httpx.post(srv.url + "/api/sessions", json={"performer": "Nope"})
        assert r.status_code == 507 and "--min-free-mb" in r.json()["detail"], r.text
        assert httpx.get(srv.url + "/api/sessions").json()["sessions"] == []


@pytest.mark.parametrize("argv,field,value", [
    (["--max-session-min", "0"], "max_session_s", None),
    (["--max-session-min", "1.5"], "max_session_s", 90.0),
    (["--min-free-mb", "2"], "min_free_bytes", 2 * 2**20),
])
def test_the_limit_options_reach_the_settings(argv, field, value):
    from flockcal.cli import build_parser
    from flockcal.commands.serve import settings_from_args

    args = build_parser().parse_args(["serve", *argv])
    assert getattr(settings_from_args(args).check(), field) == value
