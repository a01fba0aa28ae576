"""The service's events (slips and swaps, sessions, the tracker, the service itself) as one typed record from
the moment the persistence takes them to the store, the snapshots and the routes that send them.

An event is made typed where it happens (`Event.new("session", session_id=…, action="started", …)`: each
kind has fields of its own), its columns typed and its JSON object built with it, which is how the websocket
sends it (docs/service.md); the store stamps and numbers it and reads it back typed (`Event.stored`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Mapping

# The events table's own columns; every other field of an event is its payload.
COLUMNS = ("id", "session_id", "type", "time_s", "wall_time")


class _Unset:
    """`Event.new`'s time_s when the event has none of its own (None is a time not known)."""


UNSET = _Unset()


@dataclass(frozen=True, eq=False)
class Event:
    """One event with its store id. `doc` is its whole JSON object (the five columns among its fields): as it
    was made for the websocket (`Event.new`), or in the store's order for the REST lists (`Event.stored`)."""

    id: int | None
    type: str
    session_id: str | None
    time_s: float | None
    wall_time: float | None  # None until it is stored (`stamped`)
    doc: Mapping
    timed: bool = False  # its session time was given where it was made (else the live session's is taken)

    @staticmethod
    def new(type: str, *, session_id: str | None = None, time_s: float | None | _Unset = UNSET, **fields) -> "Event":
        """An event as the part of the service that made it writes it: its kind, the session it belongs to
        (none: the live one's, once stored), its session time when it has one of its own, its other fields.
        It is stamped and numbered when it is stored (`stamped`, `numbered`)."""
        timed = not isinstance(time_s, _Unset)
        time_s = time_s if timed else None
        own = {"session_id": session_id} if session_id is not None else {}
        doc = {"type": type, **own, **({"time_s": time_s} if timed else {}), **fields}
        return Event(None, type, session_id, time_s, None, doc, timed)

    def stamped(self, wall_time: float, live_id: str | None, session_time: float | None) -> "Event":
        """The event at `wall_time`: one without a session belongs to `live_id` (the live session, if any),
        at `session_time` (its newest frame's; 0 before the first) unless it has a time of its own."""
        doc = {**self.doc, "wall_time": wall_time}
        if self.session_id is not None or live_id is None:
            return Event(None, self.type, self.session_id, self.time_s, wall_time, doc, self.timed)
        time_s = self.time_s if self.timed else session_time if session_time is not None else 0.0
        return Event(None, self.type, live_id, time_s, wall_time, {**doc, "session_id": live_id, "time_s": time_s},
                     True)

    @staticmethod
    def stored(id: int, session_id: str | None, type: str, time_s: float | None, wall_time: float,
               payload: Mapping) -> "Event":
        """A row of the events table (its payload decoded), its object in the store's order: the payload's
        fields, then the columns."""
        doc = {**payload, "id": id, "session_id": session_id, "type": type, "time_s": time_s, "wall_time": wall_time}
        return Event(id, type, session_id, time_s, wall_time, doc, True)

    def numbered(self, id: int) -> "Event":
        return Event(id, self.type, self.session_id, self.time_s, self.wall_time, {**self.doc, "id": id}, self.timed)

    @property
    def payload(self) -> dict:
        """Its fields but the table's columns: what the events table keeps as JSON."""
        return {k: v for k, v in self.doc.items() if k not in COLUMNS}

    def message(self) -> str:
        """The websocket's `event` message body."""
        return json.dumps({"event": self.doc})
