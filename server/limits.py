"""Limits on recording: a maximum session length and the disk, each ending the live session cleanly
(result stored, an event saying why) instead of letting it grow without end or fill the disk.

The disk is watched once a second (`tick`, on the pipeline thread, whether or not a session records): below
`--min-free-mb`, or after any write failed for want of room (`storage_failed`), the service is *full*:
recording stops, `/api/status` says so (`disk`), and a `service` event says so (held in memory while the
database cannot be written). It clears once there is room again and what was held is stored.
This part only decides: it returns the events to record and the stop a session needs (`LimitStop`); the
pipeline records them and the session manager stops the session as a client's stop would.
"""

from __future__ import annotations

import logging
import os
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from flockcal.server.clock import ServiceClock
from flockcal.server.errors import InsufficientStorage
from flockcal.server.events import Event


@dataclass(frozen=True)
class DiskStatus:
    """The disk holding the recordings: full (a write failed, or free space fell under the reserve) since
    when and why; free bytes at the last look and the reserve kept."""

    full: bool
    free_bytes: int | None
    reserve_bytes: int
    since: float | None = None
    message: str | None = None

    @property
    def doc(self) -> dict:
        return dict(vars(self))  # its fields in order, as asdict, without its deep walk (every snapshot)

log = logging.getLogger(__name__)

DISK_CHECK_S = 1.0
# Room again means at least this much free (or the reserve, if larger): with --min-free-mb 0 a disk that
# refused a write would otherwise count as having room the next second, at 0 bytes free.
ROOM_BYTES = 2 * 2**20

__all__ = ["InsufficientStorage", "LimitStop", "SessionLimits", "free_bytes"]


def free_bytes(path: str | Path) -> int:
    """Bytes an unprivileged writer may still use on the file system holding `path`."""
    st = os.statvfs(path)
    return st.f_bavail * st.f_frsize


@dataclass(frozen=True)
class LimitStop:
    """The live session must stop: `reason` "max_length" or "disk_full" (its session event's), `message`
    (the event's, and the session's note), `time_s` its session time then (None: not known)."""

    session_id: str
    reason: str
    message: str
    time_s: float | None

    def event(self) -> Event:
        if self.time_s is None:
            return Event.new("session", session_id=self.session_id, action="limit", reason=self.reason,
                             message=self.message)
        return Event.new("session", session_id=self.session_id, time_s=self.time_s, action="limit",
                         reason=self.reason, message=self.message)


class SessionLimits:
    """`max_session_s` (None: no maximum) and `min_free_bytes` kept free on the recordings' disk. Its
    methods return the events to record (`tick`, `storage_failed`) and the stop a session needs (`check`)."""

    def __init__(self, recordings: Path, max_session_s: float | None, min_free_bytes: int, clock: ServiceClock):
        self.recordings = Path(recordings)
        self.clock = clock  # the look's cadence and how long the disk was full; its stamps for `since`
        self.max_session_s = max_session_s
        self.min_free_bytes = int(min_free_bytes)
        self._stopping: str | None = None  # the session a stop was asked for (once per session)
        self._lock = threading.Lock()  # the disk state: set from any thread, cleared by tick
        self._last_tick: float | None = None
        self.free: int | None = None
        self.full_since: float | None = None  # the stamp of when the disk became full, None while there is room
        self._full_at = 0.0  # ... on the monotonic clock
        self.full_message: str | None = None

    # --- the disk ----------------------------------------------------------------------------------
    def disk_status(self) -> DiskStatus:
        """What `/api/status` shows as `disk` (cheap: the last look, at most a second old)."""
        return DiskStatus(self.full_since is not None, self.free, self.min_free_bytes, self.full_since,
                          self.full_message)

    def storage_failed(self, why: str) -> list[Event]:
        """A write failed for want of room (the frame log, the raw recording, the database): the disk is
        full from now until `tick` finds room and stores what was held; a recording session's `check`
        stops it. Returns the event saying so, the first time."""
        return self._set_full(f"a write failed for want of room on the disk holding {self.recordings}: {why}")

    def _set_full(self, message: str) -> list[Event]:
        with self._lock:
            if self.full_since is not None:
                return []
            self.full_since, self.full_message = self.clock.stamp(), message
            self._full_at = self.clock.monotonic()
        log.warning("%s", message)
        return [Event.new("service", action="disk_full", message=message, free_bytes=self.free)]

    def tick(self, flush_held: Callable[[], bool]) -> list[Event]:
        """Look at the disk (at most once a second): full below the reserve; room again once above it and
        `flush_held()` has stored everything held in memory. Returns the events. Pipeline thread."""
        now = self.clock.monotonic()
        if self._last_tick is not None and now - self._last_tick < DISK_CHECK_S:
            return []
        self._last_tick = now
        try:
            self.free = free = free_bytes(self.recordings)
        except OSError as exc:
            log.warning("cannot look at the disk holding %s: %s", self.recordings, exc)
            return []
        if free < self.min_free_bytes:
            return self._set_full(f"only {free / 2**20:.1f} MB free on the disk holding {self.recordings}, below the "
                                  f"{self.min_free_bytes / 2**20:g} MB the service keeps free (--min-free-mb): "
                                  "recording stops and no session starts until there is room")
        if self.full_since is None or free < ROOM_BYTES or not flush_held():
            return []
        with self._lock:
            full_at, self.full_since, self.full_message = self._full_at, None, None
        message = (f"room again on the disk holding {self.recordings} ({free / 2**20:.0f} MB free, full for "
                   f"{max(now - full_at, 0.0):.0f} s): sessions can start")
        log.warning("%s", message)
        return [Event.new("service", action="disk_ok", message=message, free_bytes=free)]

    # --- before a session starts (request thread) ----------------------------------------------
    def check_start(self) -> None:
        """InsufficientStorage (507) when the recordings' disk is already at the reserve, or full."""
        free = free_bytes(self.recordings)
        if free < self.min_free_bytes:
            raise InsufficientStorage(
                f"only {free / 2**20:.0f} MB free on the disk holding {self.recordings}, below the "
                f"{self.min_free_bytes / 2**20:.0f} MB the service keeps free (--min-free-mb); free some space "
                "(DELETE old sessions) before starting a session")
        if self.full_since is not None:
            raise InsufficientStorage(f"the disk is full: {self.full_message}; free some space (DELETE old sessions) "
                                      "before starting a session")

    # --- while recording (pipeline thread) -------------------------------------------------------
    def check(self, session_id: str, time_s: float | None) -> LimitStop | None:
        """The stop the live session needs, once per session: at its maximum length, or on a full disk."""
        if self._stopping == session_id:
            return None
        if self.max_session_s is not None and time_s is not None and time_s >= self.max_session_s:
            return self._stop(session_id, "max_length", f"session {session_id} stopped: it reached the maximum "
                              f"length of {self.max_session_s / 60:g} min (--max-session-min)", time_s)
        if self.full_since is not None:
            return self._stop(session_id, "disk_full", f"session {session_id} stopped: {self.full_message}", time_s)
        return None

    def _stop(self, session_id: str, reason: str, message: str, time_s: float | None) -> LimitStop:
        self._stopping = session_id
        log.warning("%s", message)
        return LimitStop(session_id, reason, message, time_s)
