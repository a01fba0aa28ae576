"""A sensor slip injected into the simulated performer through the API reaches the operator: a "slip"
event on the websocket and in the session's events naming the sensor, and in the stored result.
"""

from __future__ import annotations

import asyncio
import json
import time

import httpx
import websockets

from flockcal.server.settings import Settings
from server_helpers import ServerThread, free_port, wait_connected

SENSOR = "l_forearm"


def test_injected_slip_is_reported_live_and_stored(tmp_path):
    settings = Settings(device="sim://slip?birds=16&motion=exercise&rate=100&baud=921600&seed=4", birds=16,
                        http_port=free_port(), data_dir=tmp_path)
    with ServerThread(settings) as srv:
        wait_connected(srv.url)
        # The known human hierarchy: joints are right from the first fit, so the monitor can settle.
        r = httpx.post(srv.url + "/api/sessions", json={"performer": "Eve", "skeleton": "human"})
        assert r.status_code == 201, r.text
        sid = r.json()["id"]
        ws_url = srv.url.replace("http://", "ws://") + "/ws/live"

        async def watch() -> dict:
            async with websockets.connect(ws_url) as ws:
                await ws.send(json.dumps({"type": "subscribe", "rate_hz": 10, "content": ["events", "status"]}))
                deadline = time.monotonic() + 40
                slipped = False
                while time.monotonic() < deadline:
                    msg = json.loads(await asyncio.wait_for(ws.recv(), 5))
                    if msg["type"] == "status" and not slipped and msg["status"]["session"]["time_s"] > 11:
                        r = await asyncio.to_thread(httpx.post, srv.url + "/api/simulator/slip",
                                                    json={"sensor": SENSOR, "distance_m": 0.03})
                        assert r.status_code == 200, r.text
                        slipped = True
                    if msg["type"] == "event" and msg["event"]["type"] == "slip":
                        assert slipped, f"slip reported before one was injected: {msg}"
                        return msg["event"]
                raise AssertionError("no slip event within 40 s")

        event = asyncio.run(watch())
        stored = httpx.get(srv.url + f"/api/sessions/{sid}/events").json()["events"]
        httpx.post(srv.url + f"/api/sessions/{sid}/stop", timeout=30)
        result = httpx.get(srv.url + f"/api/sessions/{sid}/result").json()
    assert event["sensor"] == SENSOR or SENSOR in event["candidates"]
    assert event["session_id"] == sid and event["jump_mm"] > 5 and event["joints"]
    assert any(e["type"] == "slip" and e["id"] == event["id"] for e in stored)
    assert any(s["sensor"] == event["sensor"] and abs(s["time_s"] - event["time_s"]) < 1e-3
               for s in result["slip_events"])
    # The slipped sensor's joints were refitted on the frames since the slip (a new segment).
    touched = [j for j in result["joints"] if event["sensor"] in (j["child"], j["parent"])]
    assert touched and all(abs(j.get("segment_start_s", -1) - event["time_s"]) < 1e-3 for j in touched)
