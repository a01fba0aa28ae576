"""The service's memory figures (server/memory.py) and its hand-back of freed heap (flockcal/malloc.py), tried
in a fresh Python process so nothing else this suite allocated is in the way; /api/status reporting them from a
real service; and the service trimming between sessions but not while one records, on its own clock.
"""

from __future__ import annotations

import json
import subprocess
import sys

import httpx
import pytest

from flockcal.server.settings import Settings
from server_helpers import ServerProcess, free_port, manual_service, run_clock, start_session, status, wait_connected
from service_process import wait_for

FRAGMENT = r"""
import json
from flockcal.malloc import release_free_heap
from flockcal.server.memory import process_memory
blobs = [bytes(2000) for _ in range(40000)]  # ~80 MB through malloc itself (over pymalloc's 512 bytes)
keep = bytes(2000)  # allocated after them: the heap's top stays in use, so free() cannot shrink it alone
full = process_memory()["rss_mb"]
del blobs
freed = process_memory()["rss_mb"]
print(json.dumps({"full": full, "freed": freed, "released": release_free_heap(), "after": process_memory()["rss_mb"]}))
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="malloc_trim and /proc are glibc/Linux")
def test_freed_heap_stays_resident_until_released_and_then_leaves():
    # What a season at the kiosk does in small steps: large temporaries freed in the middle of the heap.
    out = json.loads(subprocess.run([sys.executable, "-c", FRAGMENT], capture_output=True, text=True,
                                    check=True, timeout=60).stdout)
    assert out["released"] is True
    assert out["freed"] > out["full"] - 20  # glibc kept (nearly) all 80 MB after free()
    assert out["after"] < out["freed"] - 50  # and handed at least 50 of them back when asked


def test_api_status_reports_the_services_memory(tmp_path):
    port = free_port()
    server = ServerProcess(["--data-dir", str(tmp_path / "data")], port)  # the built-in simulator
    server.start()
    try:
        wait_connected(server.url, timeout=60)
        proc = httpx.get(server.url + "/api/status", timeout=10).json()["process"]
        status = open(f"/proc/{server.proc.pid}/status").read() if sys.platform.startswith("linux") else ""
        rss_kb = next((int(line.split()[1]) for line in status.splitlines() if line.startswith("VmRSS:")), None)
        if rss_kb is not None:  # the kernel's own figure, read from outside, within 10 % (it moves)
            assert proc["rss_mb"] == pytest.approx(rss_kb / 1024, rel=0.1)
        assert proc["python_blocks"] > 10_000  # a running service holds far more live objects than that
        assert proc["threads"] >= 3  # uvicorn's loop, the tracker reader, the pipeline at least
    finally:
        server.stop()


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="malloc_trim is glibc's")
def test_the_service_trims_freed_heap_after_a_session_and_not_while_it_records(tmp_path):
    # Tried: one session recording for 65 s of the service's clock (moved by the test), the housekeeping pass
    # looking every 5 s (13 passes): no trim while it records (a trim holds the pipeline's arena locks), one
    # at once when it stops (the stop wakes the pass), and /api/status counts them with what they took.
    settings = Settings(device="sim://trim?birds=4&motion=walk&rate=144&baud=921600", birds=4, baud=921600,
                        http_port=free_port(), data_dir=tmp_path, retention_interval_s=5.0)
    with manual_service(settings) as (srv, clock):
        url = srv.url
        wait_for(lambda: status(url)["retention"]["heap_trims"] >= 1, 30, "the first pass's trim, before any session")
        sid = start_session(url, performer="Long")
        before = status(url)["retention"]["heap_trims"]
        run_clock(clock, 65.0, dt=0.25)
        during = status(url)["retention"]
        assert httpx.get(url + f"/api/sessions/{sid}", timeout=10).json()["state"] == "live"
        assert during["heap_trims"] == before, during
        assert httpx.post(url + f"/api/sessions/{sid}/stop", timeout=30).status_code == 200
        after = wait_for(lambda: (st := status(url)["retention"])["heap_trims"] > before and st, 30,
                         "a trim in the gap after the session stopped (the stop wakes the housekeeping pass)")
        assert after["heap_trim_ms_max"] >= after["heap_trim_ms_mean"] >= 0.0
