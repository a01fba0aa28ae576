"""Websocket admission and teardown: client slots counted per role after authentication, and a handle
on each connection's transport so a client that stopped reading can be cut off for good.

Sockets still waiting for a token get a small pool of their own, so they cannot take the slots of
authenticated clients; a stalled client's transport is aborted (its queued bytes discarded, the socket
closed) instead of waiting on a close handshake the client will never read.
"""

from __future__ import annotations

import socket
import struct
import threading
from collections import OrderedDict

ROLES = ("admin", "kiosk", "read")
PENDING_KEY = "waiting for a token"


class ClientSlots:
    """`max_per_role` websocket clients per role, and `max_pending` sockets that have no token yet.

    When the pending pool is full the socket waiting longest gives way to the newcomer: a client that
    sends its token in its first message gets in however many idle sockets an attacker holds open."""

    def __init__(self, max_per_role: int, max_pending: int = 32):
        self.limits = {**{r: max_per_role for r in ROLES}, PENDING_KEY: max_pending}
        self.counts = dict.fromkeys(ROLES, 0)
        self.pending: OrderedDict[int, object] = OrderedDict()  # id(connection) -> connection, oldest first
        self._lock = threading.Lock()

    def take(self, kind: str, owner) -> tuple[bool, object | None]:
        """Take a slot of `kind` (a role, or PENDING_KEY) for `owner` → (taken, a pending owner evicted
        to make room, whom the caller must close)."""
        with self._lock:
            if kind == PENDING_KEY:
                evicted = None
                if len(self.pending) >= self.limits[PENDING_KEY]:
                    _key, evicted = self.pending.popitem(last=False)
                self.pending[id(owner)] = owner
                return True, evicted
            if self.counts[kind] >= self.limits[kind]:
                return False, None
            self.counts[kind] += 1
            return True, None

    def give_back(self, kind: str | None, owner) -> None:
        with self._lock:
            if kind == PENDING_KEY:
                self.pending.pop(id(owner), None)
            elif kind is not None:
                self.counts[kind] -= 1

    def full_message(self, kind: str) -> str:
        if kind == PENDING_KEY:
            return (f"more than {self.limits[kind]} sockets were waiting for a token; this one waited longest. "
                    "Send the token with ?token= or in the first subscribe message")
        return f"the service has its {self.limits[kind]} {kind}-token clients already; try again later"


TRANSPORT_KEY = "flockcal.transport"


class TransportHandle:
    """ASGI middleware: puts the server's transport of a websocket or HTTP connection into its scope (a
    stalled websocket client, or a download's client that stopped reading, is cut off through it).

    uvicorn hands the app its protocol's bound `send`; the protocol owns the asyncio transport. ASGI
    offers no way to abort a connection, and a close frame cannot get past a full send buffer."""

    def __init__(self, app):
        self.app = app

    async def __call__(self, scope, receive, send):
        # An HTTP request's send is wrapped by Starlette before it gets here: the connection guard
        # (server/connections.py) puts its transport into the scope instead.
        if scope["type"] in ("websocket", "http") and scope.get(TRANSPORT_KEY) is None:
            scope[TRANSPORT_KEY] = getattr(getattr(send, "__self__", None), "transport", None)

        return await self.app(scope, receive, send)


def abort(scope) -> bool:
    """Abort the connection's transport (no close handshake); False when the server offers none."""
    transport = scope.get(TRANSPORT_KEY)
    if transport is None:
        return False
    sock = transport.get_extra_info("socket")
    if sock is not None:
        try:
            # Linger 0: the kernel resets the connection and frees its queued bytes now. A plain close
            # leaves an orphan that keeps retrying those bytes into the client's closed window.
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        except OSError:
            pass
    transport.abort()
    return True
