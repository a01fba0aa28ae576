"""WebSocket /ws/live: each client subscribes to a rate and content; messages carry type, seq, time.

One sender task per client reads the hub's newest snapshot when its rate allows, so a slow client
only skips snapshots; it never slows the pipeline or the others. Protocol: README.md, "WebSocket /ws/live".
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
import time

from fastapi import APIRouter, WebSocket, WebSocketDisconnect

from flockcal.server.auth import origin_allowed, token_role
from flockcal.server.snapshot import Snapshot, residual_message

router = APIRouter()
log = logging.getLogger(__name__)

CONTENT = ("status", "fit", "residuals", "events", "pose")
STATUS_PERIOD_S = 0.5  # status goes out at most twice a second (and at once when it changes)
AUTH_TIMEOUT_S = 10.0
REPLAY_EVENTS = 20  # recent events of the live session sent on subscribe


class Subscription:
    def __init__(self, rate_hz: float, content: tuple[str, ...]):
        self.rate_hz = rate_hz
        self.content = content


def parse_subscribe(msg: dict, max_rate: float) -> Subscription:
    """Validate a subscribe message; ValueError with a readable reason otherwise."""
    rate = msg.get("rate_hz", 10)
    if rate is None:
        rate = max_rate
    if isinstance(rate, bool) or not isinstance(rate, (int, float)) or not math.isfinite(rate) or rate <= 0:
        raise ValueError(f"rate_hz must be a positive number (at most {max_rate:g}), got {rate!r}")
    content = msg.get("content", ["status"])
    if isinstance(content, str):
        content = [content]
    if not isinstance(content, list) or not all(isinstance(c, str) for c in content):
        raise ValueError(f"content must be a list drawn from {list(CONTENT)}")
    unknown = [c for c in content if c not in CONTENT]
    if unknown:
        raise ValueError(f"unknown content {unknown}; choose from {list(CONTENT)}")
    return Subscription(min(float(rate), max_rate), tuple(dict.fromkeys(content)))


class Connection:
    def __init__(self, ws: WebSocket, service):
        self.ws = ws
        self.service = service
        self.seq = 0
        self.sub: Subscription | None = None
        self.changed = asyncio.Event()
        self.authorised = not service.settings.token

    def envelope(self, type_: str, body_json: str | None = None, **fields) -> str:
        self.seq += 1
        head = json.dumps({"type": type_, "seq": self.seq, "time": round(time.time(), 6), **fields})
        if body_json is None or body_json == "{}":
            return head
        return head[:-1] + ", " + body_json[1:]

    async def send(self, text: str) -> None:
        try:
            # asyncio.timeout, not wait_for: no extra task per message (this runs for every snapshot).
            async with asyncio.timeout(self.service.settings.ws_send_timeout_s):
                await self.ws.send_text(text)
        except TimeoutError:
            # The client stopped reading: drop it rather than hold its backlog.
            self.service.hub.dropped_slow += 1
            log.info("dropping a websocket client that took no data for %.0f s", self.service.settings.ws_send_timeout_s)
            raise

    async def receive_loop(self) -> None:
        settings = self.service.settings
        while True:
            raw = await self.ws.receive_text()
            try:
                msg = json.loads(raw)
                if not isinstance(msg, dict):
                    raise ValueError("a message must be a JSON object")
            except ValueError as exc:
                await self.send(self.envelope("error", message=f"not a JSON object: {exc}"))
                continue
            kind = msg.get("type")
            if kind == "ping":
                await self.send(self.envelope("pong"))
                continue
            if kind != "subscribe":
                await self.send(self.envelope("error", message=f"unknown message type {kind!r}; send "
                                              '{"type": "subscribe", "rate_hz": 10, "content": ["status", "fit"]}'))
                continue
            if not self.authorised:
                token = msg.get("token")
                if not isinstance(token, str) or token_role(settings, token) is None:
                    await self.send(self.envelope("error", message="token missing or not recognised: give ?token=… "
                                                  "in the URL or \"token\" in the subscribe message"))
                    await self.ws.close(code=1008)
                    return
                self.authorised = True
            try:
                self.sub = parse_subscribe(msg, settings.publish_hz)
            except ValueError as exc:
                await self.send(self.envelope("error", message=str(exc)))
                continue
            await self.send(self.envelope("subscribed", rate_hz=self.sub.rate_hz, content=list(self.sub.content)))
            self.changed.set()

    async def send_loop(self) -> None:
        hub = self.service.hub
        while self.sub is None:
            self.changed.clear()
            try:
                await asyncio.wait_for(self.changed.wait(), None if self.authorised else AUTH_TIMEOUT_S)
            except asyncio.TimeoutError:
                await self.send(self.envelope("error", message="no subscribe message with a token arrived; closing"))
                await self.ws.close(code=1008)
                return
        sent_seq = 0
        fit_seq = -1
        residual_seq = 0
        snap = hub.latest
        event_id = self._initial_event_id(snap)
        status_at = 0.0
        status_key = None
        next_due = 0.0
        sub = None
        while True:
            if self.sub is not sub:
                sub, fit_seq, status_at = self.sub, -1, 0.0
                if "residuals" in sub.content:
                    residual_seq = _residual_start(hub.latest)
            now = time.monotonic()
            if now < next_due:
                try:
                    async with asyncio.timeout(next_due - now):
                        await self.changed.wait()
                    self.changed.clear()
                    continue
                except TimeoutError:
                    pass
            snap = await hub.wait_newer(sent_seq, timeout=1.0)
            if snap.seq <= sent_seq and not self.changed.is_set():
                continue
            self.changed.clear()
            # At the top rate every snapshot goes out as soon as it is published.
            top = sub.rate_hz >= self.service.settings.publish_hz
            next_due = 0.0 if top else time.monotonic() + 1.0 / sub.rate_hz
            sent_seq = snap.seq
            out = []
            content = sub.content
            if "status" in content:
                key = (snap.status.get("connected"), (snap.session or {}).get("id"))
                if key != status_key or time.monotonic() - status_at >= STATUS_PERIOD_S:
                    status_key, status_at = key, time.monotonic()
                    out.append(self.envelope("status", snap.status_json))
            if "fit" in content and snap.fit is not None and snap.fit_seq != fit_seq:
                fit_seq = snap.fit_seq
                out.append(self.envelope("fit", snap.fit_json))
            if "residuals" in content:
                new = [s for s in snap.residuals if s.seq > residual_seq]
                if new:
                    residual_seq = new[-1].seq
                    out.append(self.envelope("residuals", json.dumps(residual_message(new))))
            if "events" in content:
                for ev in snap.events:
                    if ev["id"] > event_id:
                        event_id = ev["id"]
                        out.append(self.envelope("event", json.dumps({"event": ev})))
            if "pose" in content and snap.pose is not None:
                out.append(self.envelope("pose", snap.pose_json))
            for text in out:
                await self.send(text)

    def _initial_event_id(self, snap: Snapshot) -> int:
        # Replay the live session's last few events so a reconnecting page shows them again.
        if snap.session is None:
            return snap.events[-1]["id"] if snap.events else 0
        mine = [e["id"] for e in snap.events if e.get("session_id") == snap.session["id"]]
        if len(mine) > REPLAY_EVENTS:
            return mine[-REPLAY_EVENTS - 1]
        return (mine[0] - 1) if mine else (snap.events[-1]["id"] if snap.events else 0)


def _residual_start(snap: Snapshot) -> int:
    """Start a new subscriber with the last few seconds of residuals."""
    return snap.residuals[-100].seq - 1 if len(snap.residuals) > 100 else 0


@router.websocket("/ws/live")
async def live(ws: WebSocket):
    service = ws.app.state.service
    settings = service.settings
    if service.hub.clients >= settings.ws_max_clients:
        await ws.close(code=1013)
        return
    if not origin_allowed(settings, ws.headers):
        await ws.close(code=1008)  # another site's page trying to read the live data
        return
    await ws.accept()
    conn = Connection(ws, service)
    token = ws.query_params.get("token")
    if settings.token and token is not None:
        if token_role(settings, token) is None:
            await ws.send_text(conn.envelope("error", message="token not recognised"))
            await ws.close(code=1008)
            return
        conn.authorised = True
    await ws.send_text(conn.envelope("hello", protocol=1, content=list(CONTENT), max_rate_hz=settings.publish_hz,
                                     auth_required=not conn.authorised))
    service.hub.clients += 1
    receiver = asyncio.create_task(conn.receive_loop())
    sender = asyncio.create_task(conn.send_loop())
    try:
        done, pending = await asyncio.wait({receiver, sender}, return_when=asyncio.FIRST_COMPLETED)
        for task in pending:
            task.cancel()
        await asyncio.gather(*pending, return_exceptions=True)
        for task in done:
            exc = task.exception()
            if exc is not None and not isinstance(exc, (WebSocketDisconnect, asyncio.TimeoutError, RuntimeError)):
                log.warning("websocket client failed: %r", exc)
    finally:
        service.hub.clients -= 1
        try:
            await ws.close()
        except Exception:  # already closed by the client or the transport
            pass
