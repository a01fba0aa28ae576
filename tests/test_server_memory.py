"""The service's memory figures (server/memory.py) and its hand-back of freed heap between guests (flockcal/malloc.py), tried
in a fresh Python process so nothing else this suite allocated is in the way; and /api/status reporting
them from a real service.
"""

from __future__ import annotations

import json
import subprocess
import sys

import httpx
import pytest

from server_helpers import ServerProcess, free_port, wait_connected

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
