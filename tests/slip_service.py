"""Slips injected into a running `flockcal serve` the way an operator would, and the delays to their
events: the driver shared by tests/test_server_slip.py and benchmarks/bench_slippage_service.py.

Client side only: REST to start the session and slip sensors, the websocket for the events.
"""

from __future__ import annotations

import asyncio
import json
import time
from dataclasses import dataclass, field
from types import SimpleNamespace

import httpx
import numpy as np
import websockets

from flockcal.simulator.body import human
from slip_scoring import attributes_slip_to


@dataclass
class Slip:
    """One injected slip and what the client saw of it; times in seconds."""

    sensor: str
    at_s: float  # the slip's sample time, session time (the slip reply's at_s)
    sample_mono: float  # the same instant on this process's monotonic clock (conservative: see `run`)
    routine_s: float | None = None  # the same instant on the simulated performer's clock
    event: dict | None = None  # the first event naming it (see `attributed`)
    arrival_mono: float | None = None
    others: list = field(default_factory=list)  # slip/swap events in its window that blame another sensor

    @property
    def arrival_s(self) -> float | None:
        """Sample time → the event's arrival at the client."""
        return None if self.arrival_mono is None else self.arrival_mono - self.sample_mono

    @property
    def detected_s(self) -> float | None:
        """Sample time → the event's own `detected_s` (session time of the frame at which it was confirmed)."""
        return None if self.event is None else self.event["detected_s"] - self.at_s

    @property
    def onset_error_s(self) -> float | None:
        return None if self.event is None else self.event["time_s"] - self.at_s


def human_tree() -> tuple[tuple[str, ...], np.ndarray]:
    """The simulated performer's names and true parents (the oracle: the service is given no tree)."""
    model = human()
    return tuple(model.names), np.asarray(model.parent)


def spread_order(names, parent) -> list[str]:
    """All sensors, ordered so that no two in a row share a joint: a joint is then hit by two slips
    at least two spacings apart, so it has re-baselined on its new segment in between."""
    left, order = list(names), []
    idx = {n: i for i, n in enumerate(names)}

    def neighbours(a: str, b: str) -> bool:
        i, j = idx[a], idx[b]
        return parent[i] == j or parent[j] == i

    while left:
        pick = next((n for n in left if not order or not neighbours(order[-1], n)), left[0])
        order.append(pick)
        left.remove(pick)
    return order


def attributed(event: dict, sensor: str, names, parent) -> bool:
    """The event blames `sensor` (or offers a leaf with its parent), as solver/slippage/monitor.py scores it."""
    ev = SimpleNamespace(sensor=event.get("sensor"), candidates=event.get("candidates") or [])
    return attributes_slip_to(ev, sensor, names, parent)


def schedule(start_s: float, warmup_s: float, spacing_s: float, moments, period_s: float) -> list[float]:
    """Times on the performer's clock for slips at `moments` of its routine (seconds into its loop of
    `period_s`), in order: each the first time at that moment of the loop that is `warmup_s` after the
    session's start (`start_s`, on the same clock) and `spacing_s` after the slip before it."""
    out, earliest = [], start_s + warmup_s
    for phase in moments:
        at = phase + period_s * np.ceil((earliest - phase) / period_s - 1e-9)
        out.append(float(at))
        earliest = at + spacing_s
    return out


def run(url: str, sensors: list[str], *, warmup_s: float = 20.0, spacing_s: float = 10.0,
        distance_m: float = 0.02, follow_s: float = 3.0, performer: str = "slip bench",
        moments=None, log=None) -> tuple[str, list[Slip], list[dict]]:
    """Start a session (automatic topology), slip each of `sensors` once, in turn, from `warmup_s` of
    session time on, and listen until the service has processed `follow_s` of frames past the last one
    (at most a minute more). Returns (session id, the slips with their events, every slip/swap event
    received).

    With `moments` (one per sensor: seconds into the performer's routine loop) the slips are scheduled
    on the performer's own clock through the API, at those moments of its routine and at least
    `spacing_s` apart (`schedule`): the moment a slip lands on then does not depend on how late the
    session started or how loaded the machine is. Without, each is sent when the session has run
    `warmup_s`, then `spacing_s` of wall time apart, and lands on whatever moment that is.

    A slip's sample time on this clock is taken as (request sent) + the reply's `in_s` (seconds from
    the reply to the sample): the request's own transit is counted into the delay, never out of it."""
    names, parent = human_tree()
    if moments is not None and len(moments) != len(sensors):
        raise ValueError("one moment per sensor")
    r = httpx.post(url + "/api/sessions", json={"performer": performer}, timeout=30)
    r.raise_for_status()
    sid = r.json()["id"]
    ws_url = url.replace("http://", "ws://") + "/ws/live"
    slips: list[Slip] = []
    received: list[tuple[float, dict]] = []

    async def session_time(ws) -> float:
        while True:
            msg = json.loads(await asyncio.wait_for(ws.recv(), 30))
            if msg["type"] == "event":
                received.append((time.monotonic(), msg["event"]))
            elif msg["type"] == "status" and (msg["status"].get("session") or {}).get("id") == sid:
                return float(msg["status"]["session"]["time_s"])

    async def listen(ws, until: float) -> None:
        while time.monotonic() < until:
            try:
                msg = json.loads(await asyncio.wait_for(ws.recv(), max(until - time.monotonic(), 0.01)))
            except asyncio.TimeoutError:
                return
            if msg["type"] == "event":
                received.append((time.monotonic(), msg["event"]))

    async def slip(client, name: str, at_routine_s: float | None = None) -> None:
        sent = time.monotonic()
        body = {"sensor": name, "distance_m": distance_m}
        if at_routine_s is not None:
            body["at_routine_s"] = at_routine_s
        rep = await client.post(url + "/api/simulator/slip", json=body)
        rep.raise_for_status()
        got = rep.json()
        if got["session_id"] != sid or got["at_s"] is None or got["in_s"] is None:
            raise AssertionError(f"the slip reply names no sample time in session {sid}: {got}")
        slips.append(Slip(name, got["at_s"], sent + got["in_s"], routine_s=got["routine_s"]))
        if log:
            log(f"  slipped {name} at {got['at_s']:.2f} s (routine clock {got['routine_s']:.2f} s)")

    async def main() -> None:
        async with websockets.connect(ws_url, max_size=None) as ws:
            await ws.send(json.dumps({"type": "subscribe", "rate_hz": 5, "content": ["events", "status"]}))
            async with httpx.AsyncClient(timeout=30) as client:
                if moments is not None:
                    # The session's start on the performer's clock: its clock now less the session's time now
                    # (both read after the session has frames; the pipeline's lag only shortens the warm-up
                    # by as much, never moves a slip's moment of the routine).
                    now_s = await session_time(ws)
                    while now_s <= 0:
                        now_s = await session_time(ws)
                    sim = (await client.get(url + "/api/simulator")).json()
                    start = sim["clock_s"] - now_s
                    for name, at in zip(sensors, schedule(start, warmup_s, spacing_s, moments, sim["period_s"])):
                        await slip(client, name, at)
                else:
                    while await session_time(ws) < warmup_s:
                        pass
                    for name in sensors:
                        sent = time.monotonic()
                        await slip(client, name)
                        await listen(ws, sent + spacing_s)
            # A pipeline running behind publishes late: listen until it has processed follow_s past the
            # last slip (a minute at most beyond it), so a late event counts as late, not as missed.
            until = (slips[-1].at_s + (0.0 if moments is not None else spacing_s) + follow_s) if slips else 0.0
            deadline = time.monotonic() + 60.0 + max(until - await session_time(ws), 0.0)
            while time.monotonic() < deadline and await session_time(ws) < until:
                pass

    asyncio.run(main())
    events = [(t, e) for t, e in received if e.get("type") in ("slip", "swap") and e.get("session_id") == sid]
    for k, s in enumerate(slips):
        end = slips[k + 1].at_s - 0.5 if k + 1 < len(slips) else float("inf")
        for t, e in events:
            if not s.at_s - 0.5 <= e["time_s"] < end:
                continue
            if not attributed(e, s.sensor, names, parent):
                s.others.append(e)
            elif s.event is None:
                s.event, s.arrival_mono = e, t
    return sid, slips, [e for _, e in events]
