"""The live session to disk: events into the store (and the ring of recent ones the snapshots show),
residual rows and frame counts into SQLite once a second, the frame log every `flush_s`.
Pipeline thread only; the store serialises its own writes.

When the database cannot be written (a full disk, a damaged file) nothing here raises: events are held in
memory with the ids they will be stored under (the websocket shows them meanwhile), residual rows wait in
the session, and `flush_held` stores them once it can.
"""

from __future__ import annotations

import logging
from collections import deque
from typing import Callable

from flockcal.server.clock import ServiceClock
from flockcal.server.errors import InsufficientStorage, ServerError
from flockcal.server.events import Event
from flockcal.server.fitting import json_safe
from flockcal.server.live_session import LiveSession
from flockcal.server.store import Store
from flockcal.solver.slippage.monitor import SlipEvent, SwapEvent

log = logging.getLogger(__name__)

RECENT_EVENTS = 200
DB_FLUSH_S = 1.0
MAX_HELD_EVENTS = 10_000  # events kept in memory while the database cannot take them (oldest go first)
MAX_HELD_RESIDUALS = 72_000  # residual rows likewise: an hour at 20 a second


def slip_event(event: SlipEvent | SwapEvent) -> Event:
    """A slip or swap event as the store and the websocket have it: its §5 `slip_events` entry with its
    kind as the event's type (the events table's column, the websocket message's field)."""
    entry = json_safe(event.to_dict())
    return Event.new(event.kind, **{k: v for k, v in entry.items() if k != "kind"})


class Persistence:
    """Writes the live session out; owns the recent events and the time of the last database flush.
    `on_storage_failed(exc)` hears of a write that failed for want of room."""

    def __init__(self, store: Store, clock: ServiceClock,
                 on_storage_failed: Callable[[Exception], None] | None = None):
        self.store = store
        self.clock = clock
        self.stamp = clock.stamp  # events' wall_time: the service clock's stamps, which never step back
        self.on_storage_failed = on_storage_failed
        self.recent: deque[Event] = deque(maxlen=RECENT_EVENTS)
        self.held_events: list[Event] = []  # shown with their ids, not yet in the database
        self._last_id: int | None = None
        self._last_db_flush = 0.0
        self._last_log_flush = 0.0

    def add_events(self, events: list[Event], live: LiveSession | None, session_time: float | None) -> None:
        """Store events (slip, session, tracker, service), each as the part that made it made it; those
        without a session belong to the live one, at `session_time` unless they carry their own."""
        rows = [ev.stamped(self.stamp(), None if live is None else live.id, session_time) for ev in events]
        ids = None
        if not self.held_events:  # otherwise they wait behind the held ones, in order
            try:
                ids = self.store.add_events(rows)
            except ServerError as exc:
                self._failed(exc, "events")
        if ids is None:
            ids = self._hold(rows)
        for ev, i in zip(rows, ids):
            self._last_id = i
            self.recent.append(ev.numbered(i))

    def _hold(self, rows: list[Event]) -> list[int]:
        if self._last_id is None:
            try:
                self._last_id = self.store.last_event_id()
            except ServerError:
                self._last_id = 0
        ids = list(range(self._last_id + 1, self._last_id + 1 + len(rows)))
        self.held_events += [ev.numbered(i) for ev, i in zip(rows, ids)]
        if len(self.held_events) > MAX_HELD_EVENTS:
            dropped = len(self.held_events) - MAX_HELD_EVENTS
            del self.held_events[:dropped]
            log.warning("%d events held in memory for the database were dropped (at most %d are held)",
                        dropped, MAX_HELD_EVENTS)
        return ids

    def flush_held(self) -> bool:
        """Store the events held in memory; True when none are left."""
        if not self.held_events:
            return True
        try:
            self.store.add_events(self.held_events)
        except ServerError:
            return False
        log.warning("%d events held in memory while the database could not be written are stored now",
                    len(self.held_events))
        self.held_events = []
        return True

    def _failed(self, exc: ServerError, what: str) -> None:
        log.warning("could not store the live session's %s: %s", what, exc)
        if isinstance(exc, InsufficientStorage) and self.on_storage_failed is not None:
            self.on_storage_failed(exc)

    def add_residuals(self, live: LiveSession, samples) -> None:
        """Residual samples (server/snapshot.py's ResidualSample) for the store's next flush."""
        live.residual_rows += [(s.time_s, s.rms_mm) for s in samples]

    def tick(self, live: LiveSession, now: float) -> None:
        """Flush what is due: the frame log every flush_s, the database once a second."""
        # Timed here on the service's clock (the log also flushes itself as frames arrive).
        if now - self._last_log_flush >= live.framelog.flush_s:
            live.framelog.flush(wait=False)  # encoded and written on the log's own thread
            self._last_log_flush = now
        if now - self._last_db_flush >= DB_FLUSH_S:
            self.flush_db(live)

    def flush_db(self, live: LiveSession) -> None:
        rows, live.residual_rows = live.residual_rows, []
        self._last_db_flush = self.clock.monotonic()
        try:
            self.store.add_residuals(live.id, rows)
        except ServerError as exc:
            live.residual_rows = (rows + live.residual_rows)[-MAX_HELD_RESIDUALS:]  # tried again next time
            self._failed(exc, "residuals")
            return
        try:
            self.store.update_session(live.id, frames=live.frames)
        except ServerError as exc:  # the count is written again next second, and at the stop
            self._failed(exc, "frame count")
