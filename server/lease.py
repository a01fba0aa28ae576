"""Session leases: a session started with `lease_s` ends that long after its client last renewed it, so a
kiosk page that was closed, crashed or unplugged does not leave a live session blocking the next guest.

A client renews with POST /api/sessions/{id}/lease; a watcher thread stops an expired session the way the
length limit does (server/limits.py): the result stored, an event and the session's note saying why.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Callable

from flockcal.server.events import Event

log = logging.getLogger(__name__)

# How often the watcher looks; a lease ends at most this much after it expires.
WATCH_S = 0.5


class SessionLeases:
    """Leases by session id on the monotonic wall clock (a page's absence is wall time, not session time).

    `stop(session_id, note=...)` stops a session (SessionManager.stop) and records why on its row in the
    same update; `add_event` queues an event."""

    def __init__(self, stop: Callable[..., object], add_event: Callable[[Event], None],
                 clock: Callable[[], float] = time.monotonic):
        self._stop = stop
        self._add_event = add_event
        self._clock = clock
        self._lock = threading.Lock()
        self._leases: dict[str, tuple[float, float]] = {}  # id → (lease_s, expires at)
        self._wake = threading.Event()
        self._thread: threading.Thread | None = None

    def grant(self, session_id: str, lease_s: float) -> None:
        with self._lock:
            self._leases[session_id] = (float(lease_s), self._clock() + float(lease_s))

    def renew(self, session_id: str) -> float | None:
        """Extend the lease by its length from now; returns that length, or None when the session has none."""
        with self._lock:
            held = self._leases.get(session_id)
            if held is None:
                return None
            self._leases[session_id] = (held[0], self._clock() + held[0])
            return held[0]

    def release(self, session_id: str) -> None:
        with self._lock:
            self._leases.pop(session_id, None)

    def remaining(self, session_id: str) -> float | None:
        """Seconds until the lease expires (None: no lease)."""
        with self._lock:
            held = self._leases.get(session_id)
        return None if held is None else max(held[1] - self._clock(), 0.0)

    def lease_s(self, session_id: str) -> float | None:
        with self._lock:
            held = self._leases.get(session_id)
        return None if held is None else held[0]

    def start(self) -> None:
        self._wake.clear()
        self._thread = threading.Thread(target=self._watch, name="fc-lease", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)

    def expired(self) -> list[str]:
        now = self._clock()
        with self._lock:
            gone = [sid for sid, (_, until) in self._leases.items() if until <= now]
            for sid in gone:
                del self._leases[sid]
        return gone

    def _watch(self) -> None:
        while not self._wake.wait(WATCH_S):
            for sid in self.expired():
                self._end(sid)

    def _end(self, session_id: str) -> None:
        message = (f"session {session_id} stopped: its client stopped renewing the lease (no "
                   "POST /api/sessions/{id}/lease in time; the kiosk page that started it went away)")
        log.warning("%s", message)
        try:
            self._add_event(Event.new("session", session_id=session_id, action="limit", reason="lease_expired",
                                      message=message))
            self._stop(session_id, note=message)
        except Exception as exc:  # stopped meanwhile by a client or a limit: nothing left to do
            log.info("lease stop of %s: %s", session_id, exc)
