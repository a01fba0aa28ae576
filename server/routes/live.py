"""WebSocket /ws/live: each client subscribes to a rate and content; messages carry type, seq, time.

One sender task per client reads the hub's newest snapshot when its rate allows, so a slow client
only skips snapshots; it never slows the pipeline or the others. Protocol: docs/service.md#websocket-wslive.
"""

from __future__ import annotations

import asyncio
import json
import logging
import math

from fastapi import APIRouter, WebSocket, WebSocketDisconnect

from flockcal.server.auth import origin_allowed, presented_role
from flockcal.server.errors import ServerError
from flockcal.server.jsonbounds import loads_bounded
from flockcal.server.models import ClientMessage
from flockcal.server.snapshot import Snapshot, residual_message
from flockcal.server.wsgate import PENDING_KEY, abort

router = APIRouter()
log = logging.getLogger(__name__)

CONTENT = ("status", "fit", "residuals", "events", "pose")
STATUS_PERIOD_S = 0.5  # status goes out at most twice a second (and at once when it changes)
AUTH_TIMEOUT_S = 10.0
REPLAY_EVENTS = 20  # recent events of the live session sent on subscribe
MAX_DEPTH = 4  # a subscribe message is one object holding a list
CLOSE_TIMEOUT_S = 1.0  # a client that does not take our close frame this fast is cut off
# rate_hz a subscription may ask for: below MIN_RATE_HZ a socket would stay silent for minutes (1e-300 Hz:
# for good); up to MAX_RATE_HZ is accepted and capped at the publish rate ("every snapshot", as 1000 asks).
MIN_RATE_HZ = 0.1
MAX_RATE_HZ = 1000.0


class Subscription:
    def __init__(self, rate_hz: float, content: tuple[str, ...]):
        self.rate_hz = rate_hz
        self.content = content


def parse_message(text: str) -> ClientMessage:
    """A client's text frame as its message; ValueError with a readable reason otherwise."""
    msg = loads_bounded(text, MAX_DEPTH, "the message")
    if not isinstance(msg, dict):
        raise ValueError(f"the message must be a JSON object, got a {type(msg).__name__}")
    return ClientMessage.model_validate(msg)


def parse_subscribe(msg: ClientMessage, max_rate: float) -> Subscription:
    """Validate a subscribe message; ValueError with a readable reason otherwise."""
    rate = msg.rate_hz
    if rate is None:
        rate = max_rate
    try:  # an integer past float's range (1 and 400 zeros) cannot be a rate either
        finite = not isinstance(rate, bool) and isinstance(rate, (int, float)) and math.isfinite(float(rate))
    except OverflowError:
        finite = False
    if not finite or not MIN_RATE_HZ <= rate <= MAX_RATE_HZ:
        raise ValueError(f"rate_hz must be a number from {MIN_RATE_HZ:g} to {MAX_RATE_HZ:g} (messages a second; "
                         f"above {max_rate:g}, the publish rate, it is capped to it), got {str(rate)[:40]}")
    content = msg.content
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
        self.slots = ws.app.state.ws_slots
        self.slot: str | None = None  # the role (or PENDING_KEY) whose slot this connection holds
        self.peer = ws.client.host if ws.client else None
        self.evicted = False
        self.role: str | None = None  # the token's role once known (admin | kiosk | read): pages say what they may do

    def check_token(self, token: str | None):
        """(role, None) for a token the service knows, else (None, why)."""
        if not isinstance(token, str) or not token:
            return None, ("token missing or not recognised: give ?token=… in the URL or \"token\" in the "
                          "subscribe message")
        try:
            return presented_role(self.service.settings, getattr(self.ws.app.state, "token_backoff", None),
                                  token, self.peer), None
        except ServerError as exc:
            return None, str(exc)

    def admit(self, kind: str) -> bool:
        """Move this connection into a slot of `kind`; False (and no slot) when they are all taken."""
        taken, evicted = self.slots.take(kind, self)
        if not taken:
            return False
        self.slots.give_back(self.slot, self)
        self.slot = kind
        if evicted is not None:
            evicted.evict()
        return True

    def evict(self) -> None:
        """Give up this socket's place in the pool of sockets waiting for a token (send_loop closes it)."""
        self.evicted = True
        self.slot = None
        self.changed.set()

    async def refuse(self, message: str, code: int) -> None:
        await self.ws.send_text(self.envelope("error", message=message))
        await self.ws.close(code=code)

    async def close(self) -> None:
        """Close with a handshake when the client takes it, else abort the transport."""
        try:
            async with asyncio.timeout(CLOSE_TIMEOUT_S):
                await self.ws.close()
        except TimeoutError:
            abort(self.ws.scope)
        except Exception:  # already closed by the client or the transport
            pass

    def envelope(self, type_: str, body_json: str | None = None, **fields) -> str:
        self.seq += 1
        # `time`: the service clock's stamp (unix s), which never steps back (docs/service.md#clock).
        head = json.dumps({"type": type_, "seq": self.seq, "time": round(self.service.clock.stamp(), 6), **fields})
        if body_json is None or body_json == "{}":
            return head
        return head[:-1] + ", " + body_json[1:]

    async def send(self, text: str) -> None:
        try:
            # asyncio.timeout, not wait_for: no extra task per message (this runs for every snapshot).
            async with asyncio.timeout(self.service.settings.ws_send_timeout_s):
                await self.ws.send_text(text)
        except TimeoutError:
            # The client stopped reading: drop it rather than hold its backlog. A close frame would
            # queue behind that backlog for ever, so the transport goes now, queued bytes and all.
            self.service.hub.dropped_slow += 1
            log.info("dropping a websocket client that took no data for %.0f s", self.service.settings.ws_send_timeout_s)
            abort(self.ws.scope)
            raise

    async def receive_loop(self) -> None:
        while True:
            message = await self.ws.receive()
            if message["type"] == "websocket.disconnect":
                raise WebSocketDisconnect(message.get("code", 1000))
            text = message.get("text")
            if text is None:
                await self.send(self.envelope("error", message="binary frames are not understood; send each message "
                                              "as a JSON text frame"))
                continue
            try:
                msg = parse_message(text)
            except ValueError as exc:
                await self.send(self.envelope("error", message=str(exc)))
                continue
            if not await self.handle(msg):
                return

    async def handle(self, msg: ClientMessage) -> bool:
        """Act on one client message; False when the connection is to close."""
        settings = self.service.settings
        kind = msg.type
        if kind == "ping":
            await self.send(self.envelope("pong"))
            return True
        if kind != "subscribe":
            shown = repr(kind)[:40] if isinstance(kind, str) else type(kind).__name__
            await self.send(self.envelope("error", message=f"unknown message type {shown}; send "
                                          '{"type": "subscribe", "rate_hz": 10, "content": ["status", "fit"]}'))
            return True
        if not self.authorised:
            role, why = self.check_token(msg.token)
            if role is None:
                await self.refuse(why, 1008)
                return False
            if not self.admit(role):
                await self.refuse(self.slots.full_message(role), 1013)
                return False
            self.authorised = True
            self.role = role
        try:
            self.sub = parse_subscribe(msg, settings.publish_hz)
        except (ValueError, TypeError) as exc:
            await self.send(self.envelope("error", message=str(exc)))
            return True
        await self.send(self.envelope("subscribed", rate_hz=self.sub.rate_hz, content=list(self.sub.content),
                                      role=self.role))
        self.changed.set()
        return True

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
            if self.evicted and not self.authorised:
                await self.refuse(self.slots.full_message(PENDING_KEY), 1013)
                return
        clock = self.service.clock  # the pacing: a client's rate and the status period
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
                # A new subscription paces from now: the old one's wait (20 s at 0.05 Hz) is not kept.
                sub, fit_seq, status_at, next_due = self.sub, -1, 0.0, 0.0
                if "residuals" in sub.content:
                    residual_seq = _residual_start(hub.latest)
            now = clock.monotonic()
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
            next_due = 0.0 if top else clock.monotonic() + 1.0 / sub.rate_hz
            sent_seq = snap.seq
            out = []
            content = sub.content
            if "status" in content:
                key = (snap.connected, snap.session and snap.session.id, snap.disk_full)
                if key != status_key or clock.monotonic() - status_at >= STATUS_PERIOD_S:
                    status_key, status_at = key, clock.monotonic()
                    out.append(self.envelope("status", snap.status_json))
            if "fit" in content and snap.has_fit and snap.fit_seq != fit_seq:
                fit_seq = snap.fit_seq
                out.append(self.envelope("fit", snap.fit_json))
            if "residuals" in content:
                new = [s for s in snap.residuals if s.seq > residual_seq]
                if new:
                    residual_seq = new[-1].seq
                    out.append(self.envelope("residuals", json.dumps(residual_message(new))))
            if "events" in content:
                for ev in snap.events:
                    if ev.id > event_id:
                        event_id = ev.id
                        out.append(self.envelope("event", ev.message()))
            if "pose" in content and snap.pose is not None:
                out.append(self.envelope("pose", snap.pose_json))
            for text in out:
                await self.send(text)

    def _initial_event_id(self, snap: Snapshot) -> int:
        # Replay the live session's last few events so a reconnecting page shows them again.
        if snap.session is None:
            return snap.events[-1].id if snap.events else 0
        mine = [e.id for e in snap.events if e.session_id == snap.session.id]
        if len(mine) > REPLAY_EVENTS:
            return mine[-REPLAY_EVENTS - 1]
        return (mine[0] - 1) if mine else (snap.events[-1].id if snap.events else 0)


def _residual_start(snap: Snapshot) -> int:
    """Start a new subscriber with the last few seconds of residuals."""
    return snap.residuals[-100].seq - 1 if len(snap.residuals) > 100 else 0


@router.websocket("/ws/live")
async def live(ws: WebSocket):
    service = ws.app.state.service
    settings = service.settings
    if not origin_allowed(settings, ws.headers):
        await ws.close(code=1008)  # another site's page trying to read the live data
        return
    await ws.accept()
    conn = Connection(ws, service)
    # Slots are counted after authentication, per role: sockets without a token wait in a pool of
    # their own, so they cannot crowd out a client that has one.
    role, why = ("admin", None) if not settings.token else (None, None)
    token = ws.query_params.get("token")
    if settings.token and token is not None:
        role, why = conn.check_token(token)
        if role is None:
            await conn.refuse(why, 1008)
            return
    kind = role or PENDING_KEY
    if not conn.admit(kind):
        await conn.refuse(conn.slots.full_message(kind), 1013)
        return
    conn.authorised = role is not None
    conn.role = role
    service.hub.clients += 1
    try:
        # `role`: what the token may do (null until a token arrives in the subscribe message), so a page knows
        # whether it may start sessions before it tries (the kiosk: docs/kiosk.md).
        await ws.send_text(conn.envelope("hello", protocol=1, content=list(CONTENT), max_rate_hz=settings.publish_hz,
                                         auth_required=not conn.authorised, role=role))
        receiver = asyncio.create_task(conn.receive_loop())
        sender = asyncio.create_task(conn.send_loop())
        done, pending = await asyncio.wait({receiver, sender}, return_when=asyncio.FIRST_COMPLETED)
        for task in pending:
            task.cancel()
        await asyncio.gather(*pending, return_exceptions=True)
        for task in done:
            exc = task.exception()
            if exc is not None and not isinstance(exc, (WebSocketDisconnect, asyncio.TimeoutError, RuntimeError)):
                log.warning("websocket client failed: %r", exc)
    except (WebSocketDisconnect, RuntimeError, OSError):
        pass
    finally:
        # The slot is given back only once the socket is gone: a client still holding one counts.
        await conn.close()
        service.hub.clients -= 1
        conn.slots.give_back(conn.slot, conn)
