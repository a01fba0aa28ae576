"""The service's events (slips and swaps, sessions, the tracker, the service itself) as one typed record from
the moment the persistence takes them to the store, the snapshots and the routes that send them.

An event is made where it happens as its JSON object (`{"type": "session", "action": "started", …}`: each
kind has fields of its own) and becomes an `Event` once, in `Event.made`: its columns typed, its object kept
in the order its fields were made, which is how the websocket sends it (docs/service.md).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Mapping

# The events table's own columns; every other field of an event is its payload.
COLUMNS = ("id", "session_id", "type", "time_s", "wall_time")


@dataclass(frozen=True, eq=False)
class Event:
    """One event with its store id. `doc` is its whole JSON object (the five columns among its fields): as it
    was made for the websocket (`Event.made`), or in the store's order for the REST lists (`Event.stored`)."""

    id: int | None
    type: str
    session_id: str | None
    time_s: float | None
    wall_time: float
    doc: Mapping

    @staticmethod
    def made(fields: Mapping, wall_time: float, session_id: str | None, time_s: float | None) -> "Event":
        """An event as a part of the service made it (`fields`, with its "type"), stamped at `wall_time`: one
        without a session belongs to `session_id` (the live one, if any), at `time_s` unless it has its own
        time. Its id comes when it is stored (`numbered`)."""
        doc = {**fields, "wall_time": wall_time}
        if session_id is not None and "session_id" not in doc:
            doc = {**doc, "session_id": session_id}
            if "time_s" not in doc:
                doc = {**doc, "time_s": time_s if time_s is not None else 0.0}
        return Event(None, str(doc["type"]), doc.get("session_id"), doc.get("time_s"), wall_time, doc)

    @staticmethod
    def stored(id: int, session_id: str | None, type: str, time_s: float | None, wall_time: float,
               payload: Mapping) -> "Event":
        """A row of the events table (its payload decoded), its object in the store's order: the payload's
        fields, then the columns."""
        doc = {**payload, "id": id, "session_id": session_id, "type": type, "time_s": time_s, "wall_time": wall_time}
        return Event(id, type, session_id, time_s, wall_time, doc)

    def numbered(self, id: int) -> "Event":
        return Event(id, self.type, self.session_id, self.time_s, self.wall_time, {**self.doc, "id": id})

    @property
    def payload(self) -> dict:
        """Its fields but the table's columns: what the events table keeps as JSON."""
        return {k: v for k, v in self.doc.items() if k not in COLUMNS}

    def message(self) -> str:
        """The websocket's `event` message body."""
        return json.dumps({"event": self.doc})
