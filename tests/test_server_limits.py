"""Recording limits (server/limits.py): a session stops cleanly at the maximum length, and before the
disk fills; both leave a stored result and an event saying why; no session starts on a full disk.

A real uvicorn on loopback with the built-in simulator; the disk is the real one the data directory
is on, its reserve set just under what is free now so that the session's own recording crosses it.
"""

from __future__ import annotations

import os

import httpx
import pytest

from flockcal.server.settings import Settings
from server_helpers import ServerThread, free_port, wait_connected
from service_process import wait_for


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


def test_recording_stops_cleanly_before_the_disk_reserve_is_reached(tmp_path):
    settings = Settings(device="sim://diskfull?birds=16&motion=exercise&rate=144&baud=921600", birds=16,
                        http_port=free_port(), data_dir=tmp_path)
    with ServerThread(settings) as srv:
        wait_connected(srv.url)
        # 16 birds at 144 Hz log ~225 kB/s; the reserve is put 1 MB below what is free at the start, so
        # the session's own frames cross it within seconds (other writers only bring the stop sooner).
        # Set on the running service: free space moves too much to fix it before the service starts.
        srv.service.limits.min_free_bytes = statvfs_free(tmp_path) - 2**20
        r = httpx.post(srv.url + "/api/sessions", json={"performer": "Disk"})
        assert r.status_code == 201, r.text
        sid = r.json()["id"]
        row = wait_stopped(srv.url, sid, 60)
        events = limit_events(srv.url, sid)
        assert row["state"] == "stopped" and row["has_result"], row
        assert [e["reason"] for e in events] == ["disk_full"] and "--min-free-mb" in events[0]["message"]
        assert "disk" in row["note"]
        # The recording is whole: its take downloads and holds every frame the row counts.
        r = httpx.get(srv.url + f"/api/sessions/{sid}/take", timeout=30)
        assert r.status_code == 200


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
