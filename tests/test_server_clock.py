"""The service under a wall clock that steps (docs/service.md#clock): durations, leases and retention ages on
the monotonic clock, stamps that never step back, each step an event.

Three ways in: the service clock alone on a `ManualClock` a test steps; the whole service in this process on
an injected stepping clock (uvicorn on loopback, the built-in simulator); and `flockcal serve` as a child
under libfaketime (Debian's `faketime`; skipped, saying so, where it is missing), its wall clock stepped an
hour forward mid-session and back again.
"""

from __future__ import annotations

import json
import os
import time

import httpx
import pytest

from flockcal.clock import ManualClock, SystemClock
from flockcal.server.clock import ServiceClock
from flockcal.server.settings import Settings
from flockcal.server.store import Store
from server_helpers import free_port, manual_service, run_clock, wait_connected

HOUR = 3600.0


def test_a_step_moves_the_offset_not_service_time_and_stamps_never_go_back():
    manual = ManualClock(wall=1.7e9, monotonic=50.0)
    clock = ServiceClock(manual)
    events = []
    clock.bind(events.append)
    first = clock.read()
    manual.advance(10.0)
    # Tried: NTP steps the wall clock an hour forward.
    manual.step_wall(HOUR)
    r = clock.read()
    assert r.service_s - first.service_s == pytest.approx(10.0)
    assert r.stamp == r.wall  # stamps follow the wall clock forward
    assert [e["action"] for e in events] == ["clock_step"] and events[0]["step_s"] == pytest.approx(HOUR)
    assert "forward by 3600.0 s" in events[0]["message"]
    # Tried: two hours back. Stamps hold, then run at half speed; service time goes on at full speed.
    manual.advance(4.0)
    manual.step_wall(-2 * HOUR)
    back = clock.read()
    assert back.stamp == pytest.approx(r.stamp + 0.5 * 4.0) and back.stamp > back.wall
    assert back.service_s - r.service_s == pytest.approx(4.0)
    assert events[-1]["step_s"] == pytest.approx(-2 * HOUR) and "half speed" in events[-1]["message"]
    stamps = [back.stamp]
    for _ in range(10):
        manual.advance(HOUR)
        stamps.append(clock.stamp())
    assert all(b > a for a, b in zip(stamps, stamps[1:]))
    # The wall clock (2 h behind, gaining 0.5 s a second on the stamps) has caught up after 4 h.
    assert clock.read().stamp == manual.wall()
    assert clock.status()["steps"] == 2 and clock.status()["stamp_ahead_s"] == 0
    # A slow drift (NTP slews at most 500 ppm) is no step.
    for _ in range(100):
        manual.advance(60.0)
        manual.step_wall(0.03)
        clock.read()
    assert len(events) == 2


class _StallingWall:
    """A ManualClock whose wall reading takes `stall` seconds for the next `stalls` readings (the thread
    descheduled inside it on a loaded machine, or a faked clock reading its file), the time read at its end."""

    def __init__(self, manual: ManualClock):
        self.manual, self.stall, self.stalls = manual, 0.0, 0

    def monotonic(self) -> float:
        return self.manual.monotonic()

    def wall(self) -> float:
        if self.stalls > 0:
            self.stalls -= 1
            self.manual.advance(self.stall)
        return self.manual.wall()

    def epoch(self):
        return self.manual.epoch()


def test_a_reading_stalled_between_the_two_clocks_is_no_step():
    manual = ManualClock(wall=1.7e9, monotonic=50.0)
    stalling = _StallingWall(manual)
    clock = ServiceClock(stalling)
    events = []
    clock.bind(events.append)
    start = clock.read()
    # Tried: one wall reading 1.5 s late (the old way, a pair of 1.5 s "steps", forward then back).
    stalling.stall, stalling.stalls = 1.5, 1
    manual.advance(1.0)
    clock.read()
    manual.advance(1.0)
    clock.read()
    # Tried: every reading of one look stalls 3 s: the wall time is known to 3 s only, still no step.
    stalling.stall, stalling.stalls = 3.0, 3
    clock.read()
    manual.advance(1.0)
    r = clock.read()
    assert events == [] and clock.status()["steps"] == 0
    assert r.service_s - start.service_s == pytest.approx(manual.monotonic() - 50.0, abs=1e-9)
    # A real step is still found, and found once, through stalled readings.
    stalling.stall, stalling.stalls = 2.0, 3
    manual.step_wall(HOUR)
    clock.read()
    manual.advance(1.0)
    clock.read()
    assert [e["step_s"] for e in events] == [pytest.approx(HOUR, abs=4.0)]


def test_the_clock_carries_across_restarts_and_finds_a_step_while_the_service_was_down(tmp_path):
    manual = ManualClock(wall=1.7e9, monotonic=100.0, epoch="boot-1")
    store = Store(tmp_path / "db.sqlite3")
    clock = ServiceClock(manual, store)
    manual.advance(30.0)
    manual.step_wall(HOUR)
    clock.read()
    clock.save()
    before = clock.read()
    # Restarted 20 s later in the same boot, the wall clock stepped forward by a day meanwhile: the boot clock
    # says 20 s passed, so the day is a step (an event), not a day of service time.
    manual.advance(20.0)
    manual.step_wall(86400.0)
    again = ServiceClock(manual, store)
    events = []
    again.bind(events.append)
    r = again.read()
    assert r.service_s - before.service_s == pytest.approx(20.0)
    assert events and events[0]["while_down"] and events[0]["step_s"] == pytest.approx(86400.0)
    again.save()
    # After a reboot (another boot id: its boot clock starts again) the wall clock's advance is downtime ...
    rebooted = ManualClock(wall=manual.wall() + 500.0, monotonic=5.0, epoch="boot-2")
    third = ServiceClock(rebooted, store)
    assert third.read().service_s - r.service_s == pytest.approx(500.0)
    third.save()
    # ... and a wall clock behind the last stamp (a flat RTC battery) is no time at all: stamps hold.
    flat = ManualClock(wall=946684800.0, monotonic=3.0, epoch="boot-3")
    fourth = ServiceClock(flat, store)
    events = []
    fourth.bind(events.append)
    r4 = fourth.read()
    assert r4.service_s == pytest.approx(third.read().service_s, abs=1e-6)
    assert r4.stamp >= third.read().stamp and events[0]["step_s"] < 0
    store.close()


def test_the_system_clock_reads_the_boot_clock():
    clock = SystemClock()
    a = clock.monotonic()
    time.sleep(0.05)
    b = clock.monotonic()
    assert 0.03 <= b - a < 5.0
    assert clock.epoch()  # the boot id: readings compare across restarts in one boot


@pytest.fixture()
def stepping_service(tmp_path):
    # The whole service on one clock the test moves (server_helpers.manual_service).
    settings = Settings(device="sim://clock?birds=4&model=linkage&motion=exercise&rate=60", birds=4,
                        http_port=free_port(), data_dir=tmp_path / "data", keep_days=0.03)
    with manual_service(settings, wall=time.time()) as (srv, manual):
        yield srv, manual


class _Times:
    """The websocket's `time` of every message, read on a thread until `close()`."""

    def __init__(self, url: str, rate_hz: float = 50):
        import threading

        from websockets.sync.client import connect

        self.times: list[float] = []
        self.ws = connect(url.replace("http", "ws") + "/ws/live").__enter__()
        self.ws.send(json.dumps({"type": "subscribe", "rate_hz": rate_hz, "content": ["status", "events"]}))
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        try:
            for text in self.ws:
                self.times.append(json.loads(text)["time"])
        except Exception:  # closed
            pass

    def close(self) -> list[float]:
        self.ws.close()
        self.thread.join(10)
        return self.times


def test_the_service_on_a_stepping_clock_keeps_durations_leases_and_recordings(stepping_service):
    srv, manual = stepping_service
    url, service = srv.url, srv.service
    watch = _Times(url)
    s = httpx.post(url + "/api/sessions", json={"performer": "Ann", "lease_s": 20}, timeout=30).json()
    run_clock(manual, 14.0, dt=0.1)
    # Tried: the wall clock steps an hour forward mid-session (NTP after boot, flat RTC battery).
    manual.step_wall(HOUR)
    run_clock(manual, 1.5, dt=0.1)  # three looks of the lease watcher, each after the step
    lease = httpx.get(url + f"/api/sessions/{s['id']}", timeout=30).json()
    assert service.leases.expired() == [] and service.leases.remaining(s["id"]) == pytest.approx(4.5)
    run_clock(manual, 0.5, dt=0.1)
    stopped = httpx.post(url + f"/api/sessions/{s['id']}/stop", timeout=30).json()
    # ... and two hours back between sessions.
    manual.step_wall(-2 * HOUR)
    run_clock(manual, 1.0, dt=0.1)
    nxt = httpx.post(url + "/api/sessions", json={"performer": "Bo"}, timeout=30).json()
    run_clock(manual, 0.5, dt=0.1)
    httpx.post(url + f"/api/sessions/{nxt['id']}/stop", timeout=30)
    run_clock(manual, 0.5, dt=0.1)
    times = watch.close()
    # The lease (20 s, 4.5 s left) is on the monotonic clock: the hour's step did not end the session.
    assert lease["state"] == "live" and stopped["state"] == "stopped"
    assert "lease" not in (stopped["note"] or "")
    # Its duration is what passed on the clock (16 s), and its stamps agree with it.
    assert stopped["duration_s"] == pytest.approx(16.0)
    assert stopped["stopped_at"] - stopped["created_at"] == pytest.approx(stopped["duration_s"])
    assert stopped["frames"] >= 0.9 * 16.0 * 60  # the tracker and the reader moved with the clock
    # The next session, started after the wall clock went back, starts no earlier than this one did.
    assert nxt["created_at"] >= stopped["created_at"]
    # Events: both steps, and wall_time never back in id order; the websocket's time never back either.
    events = httpx.get(url + "/api/events?limit=5000").json()
    steps = [e["step_s"] for e in events if e.get("action") == "clock_step"]
    assert steps == [pytest.approx(HOUR), pytest.approx(-2 * HOUR)]
    walls = [e["wall_time"] for e in events]
    assert walls == sorted(walls), walls
    assert len(times) > 10 and times == sorted(times)
    # Retention (--keep-days 0.03, 43.2 min): an hour's step forward ages nothing; 45 min of service time does.
    # (The tracker is stopped first: 45 minutes of its frames are not what this is about.)
    ret = service.retention
    ret.stop()
    service.source.stop()
    assert ret.prune_once() == []
    assert httpx.get(url + f"/api/sessions/{s['id']}/take").status_code == 200
    run_clock(manual, 45 * 60.0, dt=60.0)
    pruned = {p["id"] for p in ret.prune_once()}
    assert pruned == {s["id"], nxt["id"]}
    assert httpx.get(url + f"/api/sessions/{s['id']}/take").status_code == 410
    status = httpx.get(url + "/api/status").json()["clock"]
    assert status["steps"] == 2 and status["offset_s"] == pytest.approx(-HOUR)


# --- the real service under libfaketime --------------------------------------------------------------------
def _libfaketime() -> str | None:
    import glob

    found = sorted(glob.glob("/usr/lib/*/faketime/libfaketime.so.1")) + sorted(glob.glob("/usr/lib/faketime/libfaketime.so.1"))
    return found[0] if found else None


def _set_faketime(stamp, offset: str) -> None:
    # Replaced whole (libfaketime reads the file at each clock call: never a half-written one).
    part = stamp.with_suffix(".part")
    part.write_text(offset + "\n")
    os.replace(part, stamp)


@pytest.mark.skipif(_libfaketime() is None, reason="libfaketime is not installed (Debian: apt-get install faketime); "
                                                     "the in-process stepping-clock test above still runs")
def test_serve_under_libfaketime_stepped_an_hour_forward_mid_session_and_back(tmp_path, monkeypatch):
    # libfaketime steps the wall clock the C library reports, its monotonic clocks left alone as an NTP step
    # leaves them (FAKETIME_DONT_FAKE_MONOTONIC; its default mode moves them too, and CPython's timed waits
    # then never end). The service's clocks are the kernel's (flockcal/clock.py), read afresh each time.
    from flockcal.simulator.performer import Performer
    from flockcal.simulator.pty_tracker import PtyTracker
    from service_process import Serve, wait_for

    perf = Performer("human", "exercise", seed=1, birds=6, rate_hz=60.0, period=8.0, sta_mm=0)
    stamp = tmp_path / "faketime"
    _set_faketime(stamp, "+0")
    env = {"LD_PRELOAD": _libfaketime(), "FAKETIME_TIMESTAMP_FILE": str(stamp), "FAKETIME_NO_CACHE": "1",
           "FAKETIME_DONT_FAKE_MONOTONIC": "1"}
    for k, v in env.items():  # the child's environment (this process was started without the library)
        monkeypatch.setenv(k, v)
    tracker = PtyTracker(perf, birds=6, baud=115200, rate_hz=60.0).start()
    try:
        with Serve(["--device", tracker.device, "--birds", "6", "--names", ",".join(perf.names), "--scale", "72",
                    "--keep-days", "0.03"], free_port(), tmp_path / "serve.log") as serve:
            url = serve.url
            wait_connected(url)

            def frames(sid):
                return httpx.get(url + f"/api/sessions/{sid}", timeout=10).json()["frames"]

            def events():
                return httpx.get(url + "/api/events?limit=5000", timeout=10).json()

            def steps():
                return [e for e in events() if e.get("action") == "clock_step"]

            watch = _Times(url, rate_hz=20)
            first = httpx.post(url + "/api/sessions", json={"performer": "Ann"}, timeout=30).json()["id"]
            wait_for(lambda: frames(first) >= 60, 30, "the first session records")
            httpx.post(url + f"/api/sessions/{first}/stop", timeout=30)
            began = time.monotonic()
            second = httpx.post(url + "/api/sessions", json={"performer": "Bo"}, timeout=30).json()["id"]
            wait_for(lambda: frames(second) >= 60, 30, "the second session records")
            # Tried: the clock steps an hour forward in the middle of the second session.
            _set_faketime(stamp, "+1h")
            forward = wait_for(steps, 30, "the step forward is an event")
            assert forward[0]["step_s"] == pytest.approx(HOUR, abs=5), forward
            ran = httpx.get(url + "/api/status", timeout=10).json()["retention"]["last_run_at"]
            stopped = httpx.post(url + f"/api/sessions/{second}/stop", timeout=30).json()
            elapsed = time.monotonic() - began
            # Its duration is what passed (not an hour), and its stamps agree with it.
            assert 0 < stopped["duration_s"] <= elapsed + 0.1, (stopped, elapsed)
            assert stopped["stopped_at"] - stopped["created_at"] == pytest.approx(stopped["duration_s"], abs=1e-3)
            # --keep-days 0.03 (43 min): the pass the stop wakes prunes neither session, 2 s to a minute old.
            wait_for(lambda: (httpx.get(url + "/api/status", timeout=10).json()["retention"]["last_run_at"] or 0) > ran,
                     30, "a retention pass after the stop")
            for sid in (first, second):
                row = httpx.get(url + f"/api/sessions/{sid}", timeout=10).json()
                assert row["pruned_at"] is None and row["has_recording"], row
                assert httpx.get(url + f"/api/sessions/{sid}/take", timeout=30).status_code == 200
                assert httpx.get(url + f"/api/sessions/{sid}/raw", timeout=30).status_code == 200
            # Tried: the hour back again. Stamps never step back: events in id order, the websocket's time.
            _set_faketime(stamp, "+0")
            both = wait_for(lambda: len(s := steps()) >= 2 and s, 30, "the step back is an event")
            assert both[1]["step_s"] == pytest.approx(-HOUR, abs=5), both
            third = httpx.post(url + "/api/sessions", json={"performer": "Cy"}, timeout=30).json()
            assert third["created_at"] >= stopped["created_at"]
            wait_for(lambda: frames(third["id"]) >= 30, 30, "the third session records")
            httpx.post(url + f"/api/sessions/{third['id']}/stop", timeout=30)
            walls = [e["wall_time"] for e in events()]
            assert walls == sorted(walls)
            times = watch.close()
            assert len(times) > 20 and times == sorted(times)
            clock = httpx.get(url + "/api/status", timeout=10).json()["clock"]
            assert clock["steps"] == 2, (clock, steps())
    finally:
        tracker.stop()
