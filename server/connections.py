"""Connections to the service when clients are slow, many or hostile: every request must arrive whole
within REQUEST_DEADLINE_S, the connections stay fewer than the descriptors allow, and past that the
connection waiting longest for its request gives way to a newcomer, or the newcomer gets 503.

uvicorn has no deadline for receiving a request (its keep-alive timer is reset by any byte), so 1,100
half-sent requests held every descriptor and `/api/status` never answered. `guarded_protocol()` wraps
uvicorn's HTTP protocol with the deadline and the cap; `raise_fd_limit()` is for `flockcal serve`'s start.
"""

from __future__ import annotations

import asyncio
import json
import logging
import resource
from typing import Any

from flockcal.clock import Clock
from flockcal.server.wsgate import TRANSPORT_KEY

log = logging.getLogger(__name__)

REQUEST_DEADLINE_S = 10.0  # from a connection's first byte (or its opening) to its request's last byte
SHED_RETRY_AFTER_S = 5  # what a client turned away with 503 is told to wait
# Descriptors kept for everything but client connections: the database (with its WAL and index), the
# recordings, the tracker's ports, downloads' files, pipes, the listening socket and the event loop.
RESERVE_FDS = 192
# pyserial (the tracker's port) and the reader wait with select(), which takes no descriptor past 1023:
# with connections kept under this the tracker always reopens on a low descriptor, however high the limit.
FD_SETSIZE = 1024


def raise_fd_limit() -> tuple[int, int]:
    """Raise this process's soft limit on open files to its hard limit (a unit that sets no LimitNOFILE
    gets 1024 soft); returns (soft, hard) as they are now."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    target = hard if hard != resource.RLIM_INFINITY else max(soft, 65536)
    if target > soft:
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
        except (ValueError, OSError) as exc:  # a container may refuse; the cap below follows what is left
            log.warning("could not raise the open-files limit from %d to %d: %s", soft, target, exc)
    return resource.getrlimit(resource.RLIMIT_NOFILE)


def connection_cap(soft_limit: int | None = None) -> int:
    """How many client connections the service keeps open at once: what the descriptors allow after the
    reserve, and never so many that a descriptor reaches FD_SETSIZE."""
    if soft_limit is None:
        soft_limit = resource.getrlimit(resource.RLIMIT_NOFILE)[0]
    if soft_limit == resource.RLIM_INFINITY:
        soft_limit = FD_SETSIZE
    return max(16, min(soft_limit, FD_SETSIZE) - RESERVE_FDS)


def shed_response(retry_after: int = SHED_RETRY_AFTER_S) -> bytes:
    body = json.dumps({"detail": "the service has as many connections open as it can keep; try again in "
                                 f"{retry_after} s", "error": "unavailable"}).encode()
    return (b"HTTP/1.1 503 Service Unavailable\r\ncontent-type: application/json\r\n"
            b"retry-after: %d\r\ncontent-length: %d\r\nconnection: close\r\n\r\n" % (retry_after, len(body)) + body)


class ConnectionGuard:
    """The state all connections share: the cap, those waiting for their request, and counters that
    `/api/status` shows (`connections`)."""

    def __init__(self, cap: int, clock: Clock, deadline_s: float = REQUEST_DEADLINE_S):
        self.cap = int(cap)
        self.clock = clock  # which connection has waited longest (the deadline itself is the event loop's timer)
        self.deadline_s = float(deadline_s)
        self.open: set[GuardedConnection] = set()
        self.timed_out = 0  # requests not whole within the deadline: connection closed
        self.evicted = 0  # waiting or idle connections closed to make room for a newcomer
        self.shed = 0  # newcomers answered 503 because every connection was busy

    def status(self) -> dict:
        return {"cap": self.cap, "request_deadline_s": self.deadline_s, "http_open": len(self.open),
                "timed_out": self.timed_out, "evicted": self.evicted, "shed": self.shed}

    def make_room(self, newcomer: "GuardedConnection") -> bool:
        """True when the newcomer may stay: under the cap, or after the connection that has waited longest
        for a request (half-sent, or idle between requests) was closed for it."""
        if len(newcomer.server_state.connections) < self.cap:
            return True
        waiting = [(since, c) for c in self.open if c is not newcomer and (since := c.waiting()) is not None]
        if not waiting:
            return False
        _since, oldest = min(waiting, key=lambda x: x[0])
        oldest.close("evicted")
        self.evicted += 1
        log.warning("%d connections are open, the most the service keeps: closed the one waiting longest for "
                    "its request", self.cap)
        return True


class GuardedConnection(asyncio.Protocol):
    """uvicorn's HTTP protocol (`inner`) behind the request deadline and the connection cap. After a
    websocket upgrade the transport talks to the websocket protocol directly and this one steps aside."""

    guard: ConnectionGuard  # set on the class guarded_protocol() makes
    inner_class: type

    def __init__(self, config, server_state, app_state, _loop=None):
        self.inner = self.inner_class(config=config, server_state=server_state, app_state=app_state, _loop=_loop)
        self.server_state = server_state
        self.loop = _loop or asyncio.get_event_loop()
        self.transport: asyncio.Transport | None = None
        self.admitted = False
        self.timer: asyncio.TimerHandle | None = None
        self.waiting_since: float | None = None  # since the first byte of a request not yet whole
        self.seen_cycle: Any = None  # the last request seen whole
        self.seen_at = 0.0  # ... and when
        self.armed_cycle: Any = None

    # --- asyncio.Protocol ---------------------------------------------------------------------------
    def connection_made(self, transport) -> None:
        self.transport = transport
        if not self.guard.make_room(self):
            self.guard.shed += 1
            log.warning("every one of the %d connections is busy; a new one was answered 503", self.guard.cap)
            transport.write(shed_response())
            # Close once the client's request is in (or soon): closing on unread bytes would reset the
            # connection before the client read its 503.
            self.timer = self.loop.call_later(1.0, transport.close)
            return
        self.admitted = True
        self.guard.open.add(self)
        self.inner.connection_made(transport)
        self._arm()

    def data_received(self, data: bytes) -> None:
        if not self.admitted:
            self.transport.close()
            return
        if self.waiting_since is None or self.timer is None:
            self._arm()  # the first byte of the next request on a kept-alive connection
        self.inner.data_received(data)
        scope = getattr(self.inner, "scope", None)
        if scope is not None and TRANSPORT_KEY not in scope:
            # The app's handle on this connection (server/wsgate.py: abort), before its task first runs.
            scope[TRANSPORT_KEY] = self.transport
        if self.transport.get_protocol() is not self:  # upgraded to a websocket
            self._disarm()
            self.guard.open.discard(self)
            return
        cycle = getattr(self.inner, "cycle", None)
        if cycle is not None and cycle is not self.seen_cycle and not getattr(cycle, "more_body", True):
            self.seen_cycle, self.seen_at = cycle, self.guard.clock.monotonic()  # the request is whole: the app has it
            self._disarm()

    def eof_received(self):
        return self.inner.eof_received() if self.admitted else None

    def connection_lost(self, exc) -> None:
        self._disarm()
        if self.timer is not None:
            self.timer.cancel()
        self.guard.open.discard(self)
        if self.admitted:
            self.inner.connection_lost(exc)

    def pause_writing(self) -> None:
        if self.admitted:
            self.inner.pause_writing()

    def resume_writing(self) -> None:
        if self.admitted:
            self.inner.resume_writing()

    # --- the deadline ------------------------------------------------------------------------------
    def _arm(self) -> None:
        if self.timer is not None:
            self.timer.cancel()
        self.waiting_since = self.guard.clock.monotonic()
        self.armed_cycle = getattr(self.inner, "cycle", None)  # the request before the one now awaited
        self.timer = self.loop.call_later(self.guard.deadline_s, self._expired)

    def _disarm(self) -> None:
        if self.timer is not None:
            self.timer.cancel()
            self.timer = None
        self.waiting_since = None

    def _expired(self) -> None:
        self.timer = None
        if self.transport is None or self.transport.is_closing() or self.transport.get_protocol() is not self:
            return
        cycle = getattr(self.inner, "cycle", None)
        if cycle is not None and cycle is not self.armed_cycle and not getattr(cycle, "more_body", True):
            # A request came whole meanwhile without bytes of its own (pipelined behind the last response).
            self.seen_cycle, self.seen_at = cycle, self.guard.clock.monotonic()
            self._disarm()
            return
        if cycle is not None and not getattr(cycle, "response_complete", True) and not getattr(cycle, "more_body", True):
            # Bytes came while a response is still going out (a download): they are read after it; look again then.
            self._arm()
            return
        self.guard.timed_out += 1
        # A warning, so the log throttle (server/logthrottle.py) writes one a minute with a count.
        log.warning("closed a connection whose request was not whole within %g s", self.guard.deadline_s)
        self.close("deadline")

    def waiting(self) -> float | None:
        """Since when this connection has waited for a request (a half-sent one, or idle between requests
        after its response went out); None while a request is being answered."""
        if self.waiting_since is not None:
            return self.waiting_since
        cycle = self.seen_cycle
        if cycle is not None and getattr(cycle, "response_complete", False):
            return self.seen_at
        return None

    def close(self, why: str) -> None:
        self._disarm()
        if self.transport is not None and not self.transport.is_closing():
            self.transport.close()


def guarded_protocol(guard: ConnectionGuard, inner_class: type | None = None) -> type:
    """A protocol class for uvicorn.Config(http=…): `inner_class` (default: uvicorn's own choice) behind
    `guard`."""
    if inner_class is None:
        from uvicorn.protocols.http.auto import AutoHTTPProtocol

        inner_class = AutoHTTPProtocol
    return type("GuardedHTTPProtocol", (GuardedConnection,), {"guard": guard, "inner_class": inner_class})
