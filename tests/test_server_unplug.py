"""Unplugging the fake tracker mid-session: status says so, the session stays live, streaming resumes
when the cable is back, and no frame the service had already received is lost.
"""

from __future__ import annotations


import httpx

from flockcal.server.framelog import read_frames
from flockcal.server.settings import Settings
from server_helpers import ServerThread, free_port, wait_connected
from service_process import wait_for
from flockcal.simulator.performer import Performer
from flockcal.simulator.pty_tracker import PtyTracker


def poll(url: str, predicate, timeout: float = 30.0) -> dict:
    def met():
        st = httpx.get(url + "/api/status").json()
        return st if predicate(st) else None

    return wait_for(met, timeout, "the status asked for")


def test_unplugged_tracker_keeps_the_session_and_every_received_frame(tmp_path):
    performer = Performer("human", "exercise", seed=2, rate_hz=100.0, period=8.0, birds=6)
    pty = PtyTracker(performer, birds=6, baud=115200, rate_hz=100.0).start()
    try:
        settings = Settings(device=pty.device, birds=6, names=tuple(performer.names), http_port=free_port(),
                            data_dir=tmp_path, fast_init=True, scale_inches=72)
        with ServerThread(settings) as srv:
            wait_connected(srv.url)
            sid = httpx.post(srv.url + "/api/sessions", json={"performer": "Di"}).json()["id"]
            before = poll(srv.url, lambda s: s["session"] and s["session"]["frames"] >= 200)

            pty.disconnect()
            down = poll(srv.url, lambda s: not s["connected"])
            assert down["last_error"] and down["session"]["id"] == sid
            held = down["session"]["frames"]
            assert held >= before["session"]["frames"]
            # Nothing arrives while unplugged, and nothing received is dropped: still so once the reader has
            # tried the port again (and found it gone).
            tried = poll(srv.url, lambda s: s["reconnects"] > down["reconnects"] and not s["connected"])
            assert tried["session"]["frames"] == held

            pty.reconnect()
            up = poll(srv.url, lambda s: s["connected"] and s["session"]["frames"] >= held + 200)
            assert up["session"]["id"] == sid and up["reconnects"] >= 1

            stopped = httpx.post(srv.url + f"/api/sessions/{sid}/stop", timeout=30).json()
            events = httpx.get(srv.url + f"/api/sessions/{sid}/events").json()["events"]
            result = httpx.get(srv.url + f"/api/sessions/{sid}/result").json()
    finally:
        pty.stop()
    kinds = [e.get("kind") for e in events if e["type"] == "tracker"]
    assert "disconnected" in kinds and "connected" in kinds[kinds.index("disconnected"):]
    # Every frame taken in before, during and after the outage is in the recording and in the fit.
    _, logged = read_frames(tmp_path / "recordings" / f"{sid}.frames")
    assert len(logged) == stopped["frames"] == result["frames"] >= held + 200
    assert (logged.times[1:] >= logged.times[:-1]).all()  # in arrival order, none twice over
