"""2 cm slips injected into a real `flockcal serve` the way an operator would (a session over REST with
automatic topology, slips through POST /api/simulator/slip from 20 s on) are found in the time
docs/slippage.md measured through the service, naming the right sensor, and reach the websocket, the
session's events and the result.
"""

from __future__ import annotations

import io

import httpx
import numpy as np

from server_helpers import ServerProcess, free_port, wait_connected
from slip_service import run

# Six sensors of different kinds (a leg, the head: a leaf on the trunk, an upper arm, the trunk's root, a
# lower arm, the chest: the hub of four joints), no two in a row sharing a joint, from 20 s of session time
# on: issue #20's "from 20 s on". Each is slipped at a fixed moment of the performer's 60 s exercise loop,
# scheduled on the performer's own clock through the API (`at_routine_s`), so machine load cannot move it
# onto another moment. The moments are ones the sweep finds covered for this seed (2026-12-04,
# `python benchmarks/bench_slippage.py --phases SENSOR --routine exercise --rate 144 --seed 4 --sta-mm 12
# --between 20:79 --moments 60`, the true tree: each of these six found at 57-60 of the 60 moments, every
# miss and late find within 0-4 s, 30-34 s or 45-49 s of the loop, just after a slot of the routine
# begins; docs/slippage.md). Seconds into the loop, 11 s or more apart:
SENSORS = ["r_shin", "head", "l_upper_arm", "pelvis", "l_forearm", "chest"]
MOMENTS = [25.0, 36.0, 55.0, 6.0, 17.0, 28.0]
SPACING_S = 10.0
WARMUP_S = 20.0

# Issue #20's promise for 2 cm slips 20 s or more into a session: found, the right sensor named, median
# delay ≤ 0.5 s, worst ≤ 1.0 s. Held here on the event's own detected_s, on the performer's clock: a frame's
# session time is its arrival, which a starved host delays (at a load of 10-16 a pelvis slip's detection
# frame was stamped late enough to read 1.083 s), so the delay is counted to the detection frame's place
# on the tracker's 144 Hz grid (`on_time`), with a margin of 0.05 s: the sample time is known to a
# record's transfer time and the detector steps in 0.1 s. Arrival at the client (wall time) depends on
# the load and is a benchmark figure (benchmarks/bench_slippage_service.py), not held here.
PROMISE_MEDIAN_S, PROMISE_WORST_S, DETECTED_MARGIN_S = 0.5, 1.0, 0.05
RATE_HZ = 144.0  # the tracker's rate in the device URL below


def on_time(times: np.ndarray, t: float, since: float) -> float:
    """Session time `t` of a frame of the take (`times`, session seconds) less the host's delay in stamping
    it: frames come at the tracker's rate, and a host only ever adds delay, so the earliest-stamped frames
    since `since` place the grid, and a frame's lateness is how far it sits behind that grid."""
    k = int(np.argmin(np.abs(times - t)))  # events give times to 0.1 ms; frames are 7 ms apart
    assert abs(times[k] - t) <= 1e-4, f"no frame of the take at {t} s"
    j = np.arange(int(np.searchsorted(times, since)), k + 1)
    grid = np.min(times[j] - j / RATE_HZ)
    return t - (times[k] - (grid + k / RATE_HZ))


def test_slips_are_found_in_time_through_the_service(tmp_path):
    port = free_port()
    srv = ServerProcess(["--device", "sim://?birds=16&motion=exercise&rate=144&baud=921600&seed=4",
                         "--data-dir", str(tmp_path), "--fast-init"], port, log_path=tmp_path / "serve.log")
    srv.start()
    try:
        wait_connected(srv.url)
        # Tried: a slip with no session live; the reply says so (no session, no sample time) and is a 200.
        r = httpx.post(srv.url + "/api/simulator/slip", json={"sensor": "l_foot", "distance_m": 0.01}, timeout=30)
        assert r.status_code == 200, r.text
        assert r.json()["session_id"] is None and r.json()["at_s"] is None
        # Tried: a sensor the tracker does not have; one line naming the sensors, nothing slips.
        r = httpx.post(srv.url + "/api/simulator/slip", json={"sensor": "tail", "distance_m": 0.02}, timeout=30)
        assert r.status_code == 400 and "tail" in r.json()["detail"] and "l_forearm" in r.json()["detail"]

        sid, slips, events = run(srv.url, SENSORS, warmup_s=WARMUP_S, spacing_s=SPACING_S, follow_s=2.0,
                                 moments=MOMENTS)
        # Tried: a slip at a moment the performer has already streamed; refused, nothing slips.
        r = httpx.post(srv.url + "/api/simulator/slip", json={"sensor": "l_foot", "at_routine_s": 1.0}, timeout=30)
        assert r.status_code == 409 and "already at" in r.json()["detail"], r.text
        stored = httpx.get(srv.url + f"/api/sessions/{sid}/events", timeout=30).json()["events"]
        r = httpx.post(srv.url + f"/api/sessions/{sid}/stop", timeout=60)
        assert r.status_code == 200, r.text
        result = httpx.get(srv.url + f"/api/sessions/{sid}/result", timeout=30).json()
        take = httpx.get(srv.url + f"/api/sessions/{sid}/take", timeout=60)
        assert take.status_code == 200, take.text
        times = np.load(io.BytesIO(take.content))["times"]
    finally:
        srv.stop()

    report = {s.sensor: (s.event and (s.event["sensor"], s.event["candidates"]), s.detected_s, s.routine_s)
              for s in slips}
    # (The session's start on the performer's clock is read off a status at most 0.2 s old.)
    assert all(s.at_s >= WARMUP_S - 0.5 for s in slips), report
    # Each landed on its moment of the routine, as asked (the simulator's exercise loop is 60 s long).
    assert [round(s.routine_s % 60.0, 3) for s in slips] == MOMENTS, report
    # Every slip found, the right sensor named, and no event blaming another sensor.
    assert all(s.event is not None for s in slips), f"slips not found or blamed on another sensor: {report}"
    found = slips
    wrong = [e for s in slips for e in s.others]
    assert not wrong, f"events blaming another sensor: {wrong}"
    # From the first slip on (the promise is for 20 s and more; events in the first seconds, while the
    # fitted tree still changes, are reported in docs/slippage.md, not held here).
    later = [e for e in events if e["time_s"] >= slips[0].at_s - 0.5]
    assert len(later) == len(found), f"slip events outside the slips' windows: {later}"

    # On the performer's clock: each detection frame less its stamping delay, from 5 s before the slip on.
    detected = np.array([on_time(times, s.event["detected_s"], s.at_s - 5.0) - s.at_s for s in found])
    report["stamped late by"] = [round(s.detected_s - d, 3) for s, d in zip(found, detected)]
    assert np.all(detected > 0), report
    assert np.median(detected) <= PROMISE_MEDIAN_S + DETECTED_MARGIN_S, report
    assert detected.max() <= PROMISE_WORST_S + DETECTED_MARGIN_S, report
    # docs/slippage.md: the onset (`time_s`) is the slip time to within the 0.1 s step (median 0.00 s) on the
    # frames' own clock: held on recorded frames by test_slippage_live.py, _offline.py and _sta.py. Here the
    # frames carry their arrival time, which a loaded machine delays (one onset 0.1+ s late at load 10, the
    # slip's frame itself read late), so the service holds what load cannot move: the onset is never before
    # the slip's step and never after the event was raised.
    assert all(-0.1 <= s.onset_error_s <= s.event["detected_s"] - s.at_s for s in found), report

    # Each event is stored with the session and in its result, and its sensor's joints were refitted
    # on the frames since the slip (a new segment).
    for s in found:
        ev = s.event
        assert any(e["type"] == "slip" and e["id"] == ev["id"] for e in stored)
        assert any(x["sensor"] == ev["sensor"] and abs(x["time_s"] - ev["time_s"]) < 1e-3 for x in result["slip_events"])
        touched = [j for j in result["joints"] if ev["sensor"] in (j["child"], j["parent"])]
        assert touched and all(j.get("segment_start_s", -1) >= ev["time_s"] - 1e-3 for j in touched), (ev, touched)
