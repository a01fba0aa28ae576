"""The live session to disk: events into the store (and the ring of recent ones the snapshots show),
residual rows and frame counts into SQLite once a second, the frame log every `flush_s`.
Pipeline thread only; the store serialises its own writes.
"""

from __future__ import annotations

import time
from collections import deque

from flockcal.server.live_session import LiveSession
from flockcal.server.store import Store

RECENT_EVENTS = 200
DB_FLUSH_S = 1.0


class Persistence:
    """Writes the live session out; owns the recent events and the time of the last database flush."""

    def __init__(self, store: Store):
        self.store = store
        self.recent: deque[dict] = deque(maxlen=RECENT_EVENTS)
        self._last_db_flush = 0.0

    def add_events(self, events: list[dict], live: LiveSession | None, session_time: float | None) -> None:
        """Store events (slip, session, tracker); those without a session belong to the live one, at
        `session_time` unless they carry their own."""
        rows = []
        for ev in events:
            ev = dict(ev)
            ev.setdefault("wall_time", time.time())
            if live is not None and "session_id" not in ev:
                ev["session_id"] = live.id
                if "time_s" not in ev:
                    ev["time_s"] = session_time if session_time is not None else 0.0
            rows.append(ev)
        ids = self.store.add_events(rows)
        for ev, i in zip(rows, ids):
            ev["id"] = i
            self.recent.append(ev)

    def tick(self, live: LiveSession, now: float) -> None:
        """Flush what is due: the frame log every flush_s, the database once a second."""
        if now - live.framelog.last_flush >= live.framelog.flush_s:
            live.framelog.flush()
        if now - self._last_db_flush >= DB_FLUSH_S:
            self.flush_db(live)

    def flush_db(self, live: LiveSession) -> None:
        rows, live.residual_rows = live.residual_rows, []
        self.store.add_residuals(live.id, rows)
        self.store.update_session(live.id, frames=live.frames)
        self._last_db_flush = time.monotonic()

    def slip_events(self, live: LiveSession, fields: tuple[str, ...]) -> list[dict]:
        """The session's stored slip events, with the fields a result carries."""
        return [{k: e[k] for k in fields if k in e}
                for e in self.store.events(live.id, limit=100_000) if e["type"] == "slip"]
