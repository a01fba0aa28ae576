"""Progress over the real service (issue 21): a simulated guest does the kiosk routine from the moment a
session is started over REST; the websocket's `fit` messages, read once a second as the issue did, never say
done (nor 100 %) while a sensor still rides rigidly on a neighbour or has an undetermined joint, and name
those; done comes within the time docs/service.md "Time to calibrate" states, the session, status and
stored session say so; a slip after done undoes that sensor's joints, and every reader is told why.
"""

from __future__ import annotations

import asyncio
import json
import sqlite3
import time

import httpx
import pytest
import websockets
from hypothesis import given
from hypothesis import strategies as st

from flockcal.server.errors import ConfigError
from flockcal.server.settings import Settings
from flockcal.server.store import Store
from server_helpers import GuestSource, ServerThread, free_port, wait_connected
from flockcal.simulator.performer import Performer
from flockcal.simulator.pty_tracker import PtyTracker

RATE = 144.0
# docs/service.md "Time to calibrate": on rigid sensors a guest under the stage profile is done in a median
# 19.8 s of session time (the kiosk's p90 target is 35 s); done_at_s (session clock) gets 10 s over that.
DONE_WITHIN_S = 45.0
SLIPPED = "l_forearm"


@pytest.fixture(scope="module")
def guest():
    # Rigid sensors: the time-to-done promise (docs/service.md, "Time to calibrate") is measured on them;
    # soft tissue slows a guest down and has its own, benchmark-only figures there.
    performer = Performer("human", "kiosk", seed=33, rate_hz=RATE, height=1.81, sta_mm=0)
    tracker = PtyTracker(performer, birds=16, baud=921600, rate_hz=RATE)
    source = GuestSource(performer, tracker.flock.clock)
    tracker.flock.source = source
    tracker.start()
    yield performer, tracker, source
    tracker.stop()


@pytest.fixture(scope="module")
def server(guest, tmp_path_factory):
    performer, tracker, _ = guest
    settings = Settings(device=tracker.device, birds=16, names=tuple(performer.names), http_port=free_port(),
                        data_dir=tmp_path_factory.mktemp("progress"), fast_init=True, scale_inches=72, baud=921600)
    with ServerThread(settings) as srv:
        wait_connected(srv.url)
        yield srv


async def read_fits(url: str, sid: str, until, rate_hz: float = 1.0, timeout: float = 120.0,
                    subscribed=None) -> list[dict]:
    """The session's fit messages at `rate_hz` until `until(message)` holds; `subscribed()` is called once
    the subscription is sent (the guest starts moving then, so the first second is seen however loaded the
    machine). `timeout` (wall clock) only stops a hung test: the promises are checked on session time."""
    out = []
    deadline = time.monotonic() + timeout
    async with websockets.connect(url.replace("http://", "ws://") + "/ws/live", max_size=None) as ws:
        await ws.send(json.dumps({"type": "subscribe", "rate_hz": rate_hz, "content": ["fit"]}))
        if subscribed is not None:
            subscribed()
        while time.monotonic() < deadline:
            msg = json.loads(await asyncio.wait_for(ws.recv(), 10))
            if msg["type"] != "fit" or msg["session"]["id"] != sid:
                continue
            out.append(msg)
            if until(msg):
                return out
    raise AssertionError(f"gave up after {timeout:g} s; last: {out[-1]['missing'] if out else 'no fit'}")


def test_progress_is_honest_every_second_done_holds_and_a_slip_undoes_it(server, guest):
    performer, tracker, source = guest
    r = httpx.post(server.url + "/api/sessions", json={"performer": "Guest"})
    assert r.status_code == 201
    sid = r.json()["id"]
    try:
        check_session(server, performer, sid, source.begin)
    finally:
        httpx.post(f"{server.url}/api/sessions/{sid}/stop", timeout=30)
    # Stopped, the session keeps what it had reached when it stopped.
    stored = httpx.get(f"{server.url}/api/sessions/{sid}/progress").json()
    assert not stored["live"] and stored["done"] is False and SLIPPED in {x["joint"] for x in stored["missing"]}
    assert httpx.get(f"{server.url}/api/sessions/{sid}").json()["done"] is False


def check_session(server, performer, sid: str, begin) -> None:
    msgs = asyncio.run(read_fits(server.url, sid, lambda m: m["done"], subscribed=begin))
    done = msgs[-1]
    assert done["done_at_s"] <= DONE_WITHIN_S
    for m in msgs:
        result = m["result"]
        sensors = set(result["sensors"]) - {result["root"]}
        jointed = {j["child"] for j in result["joints"]}
        determined = {j["child"] for j in result["joints"] if j["determined"]}
        missing = {x["joint"]: x for x in m["missing"]}
        # A sensor still riding on a neighbour, or with an undetermined joint, is named, with a reason.
        for s in sensors - jointed:
            assert missing[s]["state"] == "rigid" and missing[s]["why"], (m["session"]["time_s"], missing.get(s))
        # One whose joint reads undetermined in this fit is missing, or was done and merely wobbles.
        standing = {j["joint"]: j for j in m["joint_progress"]}
        for s in sensors - determined:
            assert s in missing or standing[s]["done"]
        if m["done"]:
            assert sensors <= determined and m["progress"] == 1.0 and m["percent"] == 100
        else:
            assert m["progress"] < 1 and m["percent"] < 100 and missing
        # Missing is what is not calibrated; once every joint has been, it is those this fit leaves short,
        # still counted as calibrated and saying they wait for one fit that pins them all together.
        short = {s for s in missing if standing[s]["done"]}
        assert m["joints_needed"] == 15 and m["joints_done"] == 15 - len(set(missing) - short)
        assert not short or (m["joints_done"] == 15 and all("waiting" in missing[s]["why"] for s in short))
        assert {h["joint"] for h in m["hints"]} == set(missing) and all(h["hint"].endswith(".") for h in m["hints"])
    # The first second: most of the body has not moved, so progress is nowhere near 1. Which of
    # them still ride on a neighbour and which have moved but not turned depends on the frame the first fit
    # ends on (at 1.1 s 6 rigid and 6 not turned, at 1.4 s 2 and 10), so the two are counted together.
    unmoved = sum(x["state"] in ("rigid", "not_turned") for x in msgs[0]["missing"])
    assert msgs[0]["progress"] <= 0.2 and unmoved >= 8, (msgs[0]["session"]["time_s"], msgs[0]["missing"])
    values = [m["progress"] for m in msgs]
    assert values == sorted(values), values  # a clean take: it only goes up

    # Every reader says done: REST progress, the session row, the status, and an event.
    doc = httpx.get(f"{server.url}/api/sessions/{sid}/progress").json()
    assert doc["live"] and doc["done"] and doc["state"] == "done" and doc["missing"] == []
    row = httpx.get(f"{server.url}/api/sessions/{sid}").json()
    assert row["done"] is True and row["progress"] == 1.0
    assert httpx.get(server.url + "/api/status").json()["session"]["done"] is True
    events = httpx.get(f"{server.url}/api/sessions/{sid}/events").json()["events"]
    assert [e for e in events if e.get("action") == "calibrated"]

    # A 3 cm slip of the forearm sensor: its joints (elbow, wrist) are undone and everyone is told why.
    # The wrist's fit may be lost (reason "loss") a few tenths before the monitor confirms the slip; once it
    # has, the slip is the reason every entry of that sensor gives, the loss included.
    performer.inject_slip(SLIPPED, 0.03)
    msgs = asyncio.run(read_fits(server.url, sid, lambda m: not m["done"] and slip_undone(m), rate_hz=30,
                                 timeout=60))
    undone_at = next(k for k, m in enumerate(msgs) if not m["done"])
    assert not any(m["done"] for m in msgs[undone_at:])  # undone, done does not come back before the reason
    after = msgs[-1]
    undone = slip_undone(after)
    assert set(undone) == {SLIPPED, "l_hand"} and "slipped" in undone[SLIPPED]["why"] and after["percent"] < 100
    assert all(x["undone"]["sensor"] == SLIPPED for x in undone.values())
    hint = next(h["hint"] for h in after["hints"] if h["joint"] == SLIPPED)
    assert "left forearm sensor slipped" in hint
    events = httpx.get(f"{server.url}/api/sessions/{sid}/events").json()["events"]
    lost = [e for e in events if e.get("action") == "calibration_undone"]
    slips = [e for e in events if e.get("type") == "slip" and e.get("sensor") == SLIPPED]
    assert lost and slips and ("slipped" in lost[-1]["message"] or "no longer fits" in lost[-1]["message"])


def slip_undone(m: dict) -> dict:
    """The entries a message says a slip undid, by joint."""
    return {x["joint"]: x for x in m["missing"] if (x.get("undone") or {}).get("reason") == "slip"}



def test_progress_of_a_session_with_no_fit_yet_and_of_an_unknown_one(server):
    r = httpx.post(server.url + "/api/sessions", json={"performer": "Quick"})
    sid = r.json()["id"]
    try:
        doc = httpx.get(f"{server.url}/api/sessions/{sid}/progress").json()
        assert doc["done"] is False and doc["percent"] < 100 and doc["joints_needed"] == 15
    finally:
        httpx.post(f"{server.url}/api/sessions/{sid}/stop", timeout=30)
    # Tried: a session id that does not exist, and one with a path in it.
    r = httpx.get(f"{server.url}/api/sessions/20990101-000000-abcdef/progress")
    assert r.status_code == 404 and "GET /api/sessions" in r.json()["detail"]
    r = httpx.get(f"{server.url}/api/sessions/..%2Fetc/progress")
    assert r.status_code in (400, 404)


def test_a_target_looser_than_the_tolerance_is_refused_naming_both_options(tmp_path):
    # Tried: --target-mm 8 with the default --tolerance-mm 5 (a joint is calibrated only once determined).
    with pytest.raises(ConfigError, match=r"--target-mm .*--tolerance-mm \(5 mm\)"):
        Settings(device="sim://x?birds=3", birds=3, data_dir=tmp_path, target_m=0.008).check()
    assert Settings(device="sim://x?birds=3", birds=3, data_dir=tmp_path, target_m=0.003).check().progress_target_m == 0.003


def test_a_database_from_before_progress_was_kept_opens_and_reads_it_as_unknown(tmp_path):
    path = tmp_path / "flockcal.sqlite3"
    db = sqlite3.connect(path)
    db.executescript("""CREATE TABLE sessions (id TEXT PRIMARY KEY, performer TEXT NOT NULL, state TEXT NOT NULL,
        root TEXT, hierarchy TEXT, names TEXT NOT NULL, device TEXT NOT NULL, rate_hz REAL, created_at REAL NOT NULL,
        stopped_at REAL, frames INTEGER NOT NULL DEFAULT 0, recording TEXT, result TEXT, note TEXT);
        INSERT INTO sessions (id, performer, state, names, device, created_at) VALUES
        ('20260101-000000-aaaaaa', 'Old', 'stopped', '["a", "b"]', 'sim://', 1.0);""")
    db.commit()
    db.close()
    store = Store(path)
    try:
        (row,) = store.sessions()  # (a typed row: store.SessionRow)
        assert row.progress is None and row.done is None
        assert store.progress(row.id) is None
        store.update_session(row.id, progress={"progress": 0.5, "done": False})
        assert store.session(row.id).progress == 0.5
    finally:
        store.close()


@given(st.lists(st.tuples(st.floats(0.0, 3.0), st.sampled_from([0.0, 0.05, 0.1, 0.2, 0.3, 0.5, 0.7, 0.9, 1.0])),
                min_size=1, max_size=300),
       st.lists(st.booleans(), min_size=300, max_size=300))
def test_the_stall_clock_is_the_plain_backward_search_over_the_kept_history(steps, done_at):
    # The stall clock searches a pruned list of candidates (a plateau's 80 s of history was scanned on every
    # fit); it must give what the plain rule gives: the newest kept entry at least STALL_GAIN below the figure
    # now, else the oldest kept one (history older than 10 STALL_S trimmed, cleared once done).
    from collections import deque

    from flockcal.solver.progress_tracker import ProgressTracker

    STALL_S, STALL_GAIN = 8.0, 0.1  # the documented stall: under 10 points gained in 8 s

    tracker = ProgressTracker(0.005)
    plain: deque = deque()
    time_s = 0.0
    for (dt, figure), done in zip(steps, done_at):
        time_s += dt * STALL_S / 2  # some steps jump past the trimming horizon
        doc = {"done": done and figure == 1.0, "progress": figure, "missing": []}
        doc["stalled_s"] = tracker.stall.tick(doc["progress"], doc["done"], time_s)
        if doc["done"]:
            plain.clear()
        plain.append((time_s, figure))
        while len(plain) > 2 and plain[1][0] <= time_s - 10 * STALL_S:
            plain.popleft()
        since = next((t for t, p in reversed(plain) if p <= figure - STALL_GAIN), plain[0][0])
        idle = time_s - since
        assert doc["stalled_s"] == (round(idle, 1) if idle >= STALL_S and not doc["done"] else None)
