"""Limits on recording: a maximum session length and the disk, each stopping the live session cleanly
(result stored, an event saying why) instead of letting it grow without end or fill the disk.

The disk is watched once a second (`tick`, on the pipeline thread, whether or not a session records): below
`--min-free-mb`, or after any write failed for want of room (`storage_failed`), the service is *full*:
recording stops, `/api/status` says so (`disk`), and a `service` event says so (held in memory while the
database cannot be written). It clears once there is room again and what was held is stored.
The stop itself runs on a thread of its own, as a client's stop would.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from pathlib import Path
from typing import Callable

from flockcal.server.errors import InsufficientStorage

log = logging.getLogger(__name__)

DISK_CHECK_S = 1.0
# Room again means at least this much free (or the reserve, if larger): with --min-free-mb 0 a disk that
# refused a write would otherwise count as having room the next second, at 0 bytes free.
ROOM_BYTES = 2 * 2**20

__all__ = ["InsufficientStorage", "SessionLimits", "free_bytes"]


def free_bytes(path: str | Path) -> int:
    """Bytes an unprivileged writer may still use on the file system holding `path`."""
    st = os.statvfs(path)
    return st.f_bavail * st.f_frsize


class SessionLimits:
    """`max_session_s` (None: no maximum) and `min_free_bytes` kept free on the recordings' disk.

    `stop(session_id)` stops a session (SessionManager.stop); `add_event` queues an event and
    `set_note` records why on the session's row; `flush_held()` stores what was held in memory while
    the disk was full and says whether all of it is stored now."""

    def __init__(self, recordings: Path, max_session_s: float | None, min_free_bytes: int,
                 stop: Callable[[str], object], add_event: Callable[[dict], None],
                 set_note: Callable[[str, str], None] | None = None,
                 flush_held: Callable[[], bool] | None = None):
        self.recordings = Path(recordings)
        self.max_session_s = max_session_s
        self.min_free_bytes = int(min_free_bytes)
        self._stop = stop
        self._add_event = add_event
        self._set_note = set_note
        self.flush_held = flush_held
        self._stopping: str | None = None  # the session a stop was begun for (once per session)
        self._lock = threading.Lock()  # the disk state: set from any thread, cleared by tick
        self._last_tick = 0.0
        self.free: int | None = None
        self.full_since: float | None = None  # wall time the disk became full, None while there is room
        self.full_message: str | None = None

    # --- the disk ----------------------------------------------------------------------------------
    def disk_status(self) -> dict:
        """What `/api/status` shows as `disk` (cheap: the last look, at most a second old)."""
        return {"full": self.full_since is not None, "free_bytes": self.free, "reserve_bytes": self.min_free_bytes,
                "since": self.full_since, "message": self.full_message}

    def storage_failed(self, why: str, session_id: str | None = None, time_s: float | None = None) -> None:
        """A write failed for want of room (the frame log, the raw recording, the database): the disk is
        full from now until `tick` finds room and stores what was held; a recording session stops."""
        self._set_full(f"a write failed for want of room on the disk holding {self.recordings}: {why}")
        if session_id is not None:
            self._begin_stop(session_id, "disk_full", f"session {session_id} stopped: {self.full_message}", time_s)

    def _set_full(self, message: str) -> None:
        with self._lock:
            if self.full_since is not None:
                return
            self.full_since, self.full_message = time.time(), message
        log.warning("%s", message)
        self._add_event({"type": "service", "action": "disk_full", "message": message, "free_bytes": self.free})

    def tick(self) -> None:
        """Look at the disk (at most once a second): full below the reserve; room again once above it and
        everything held in memory is stored. Pipeline thread."""
        now = time.monotonic()
        if now - self._last_tick < DISK_CHECK_S:
            return
        self._last_tick = now
        try:
            self.free = free = free_bytes(self.recordings)
        except OSError as exc:
            log.warning("cannot look at the disk holding %s: %s", self.recordings, exc)
            return
        if free < self.min_free_bytes:
            self._set_full(f"only {free / 2**20:.1f} MB free on the disk holding {self.recordings}, below the "
                           f"{self.min_free_bytes / 2**20:g} MB the service keeps free (--min-free-mb): recording "
                           "stops and no session starts until there is room")
            return
        if self.full_since is None or free < ROOM_BYTES or (self.flush_held is not None and not self.flush_held()):
            return
        with self._lock:
            since, self.full_since, self.full_message = self.full_since, None, None
        message = (f"room again on the disk holding {self.recordings} ({free / 2**20:.0f} MB free, full for "
                   f"{time.time() - since:.0f} s): sessions can start")
        log.warning("%s", message)
        self._add_event({"type": "service", "action": "disk_ok", "message": message, "free_bytes": free})

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
    def check(self, session_id: str, time_s: float) -> None:
        if self._stopping == session_id:
            return
        if self.max_session_s is not None and time_s >= self.max_session_s:
            self._begin_stop(session_id, "max_length",
                             f"session {session_id} stopped: it reached the maximum length of "
                             f"{self.max_session_s / 60:g} min (--max-session-min)", time_s)
            return
        if self.full_since is not None:
            self._begin_stop(session_id, "disk_full", f"session {session_id} stopped: {self.full_message}", time_s)

    def _begin_stop(self, session_id: str, reason: str, message: str, time_s: float | None) -> None:
        if self._stopping == session_id:
            return
        self._stopping = session_id
        log.warning("%s", message)
        event = {"type": "session", "session_id": session_id, "action": "limit", "reason": reason, "message": message}
        if time_s is not None:
            event["time_s"] = time_s
        self._add_event(event)

        def stop():
            try:
                self._stop(session_id)
                if self._set_note is not None:
                    self._set_note(session_id, message)
            except Exception as exc:  # stopped meanwhile by a client: nothing left to do
                log.info("limit stop of %s: %s", session_id, exc)

        threading.Thread(target=stop, name="fc-limit-stop", daemon=True).start()
