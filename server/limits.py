"""Limits on recording: a maximum session length and a free-disk guard, each stopping the live session
cleanly (result stored, an event saying why) instead of letting it grow without end or fill the disk.

The pipeline calls `SessionLimits.check` after each batch of frames is logged (cheap: the disk is
looked at once a second); the stop itself runs on a thread of its own, as a client's stop would.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from pathlib import Path
from typing import Callable

from flockcal.server.errors import ServerError

log = logging.getLogger(__name__)

DISK_CHECK_S = 1.0


class InsufficientStorage(ServerError):
    status = 507
    code = "insufficient_storage"


def free_bytes(path: str | Path) -> int:
    """Bytes an unprivileged writer may still use on the file system holding `path`."""
    st = os.statvfs(path)
    return st.f_bavail * st.f_frsize


class SessionLimits:
    """`max_session_s` (None: no maximum) and `min_free_bytes` kept free on the recordings' disk.

    `stop(session_id)` stops a session (SessionManager.stop); `add_event` queues an event and
    `set_note` records why on the session's row."""

    def __init__(self, recordings: Path, max_session_s: float | None, min_free_bytes: int,
                 stop: Callable[[str], object], add_event: Callable[[dict], None],
                 set_note: Callable[[str, str], None] | None = None):
        self.recordings = Path(recordings)
        self.max_session_s = max_session_s
        self.min_free_bytes = int(min_free_bytes)
        self._stop = stop
        self._add_event = add_event
        self._set_note = set_note
        self._disk_checked = 0.0
        self._stopping: str | None = None  # the session a stop was begun for (once per session)

    # --- before a session starts (request thread) ----------------------------------------------
    def check_start(self) -> None:
        """InsufficientStorage (507) when the recordings' disk is already at the reserve."""
        free = free_bytes(self.recordings)
        if free < self.min_free_bytes:
            raise InsufficientStorage(
                f"only {free / 2**20:.0f} MB free on the disk holding {self.recordings}, below the "
                f"{self.min_free_bytes / 2**20:.0f} MB the service keeps free (--min-free-mb); free some space "
                "(DELETE old sessions) before starting a session")

    # --- while recording (pipeline thread) -------------------------------------------------------
    def check(self, session_id: str, time_s: float) -> None:
        if self._stopping == session_id:
            return
        if self.max_session_s is not None and time_s >= self.max_session_s:
            self._begin_stop(session_id, "max_length",
                             f"session {session_id} stopped: it reached the maximum length of "
                             f"{self.max_session_s / 60:g} min (--max-session-min)", time_s)
            return
        now = time.monotonic()
        if now - self._disk_checked < DISK_CHECK_S:
            return
        self._disk_checked = now
        free = free_bytes(self.recordings)
        if free < self.min_free_bytes:
            self._begin_stop(session_id, "disk_full",
                             f"session {session_id} stopped: only {free / 2**20:.0f} MB left free on the disk "
                             f"holding the recordings (the service keeps {self.min_free_bytes / 2**20:.0f} MB free, "
                             "--min-free-mb)", time_s)

    def _begin_stop(self, session_id: str, reason: str, message: str, time_s: float) -> None:
        self._stopping = session_id
        log.warning("%s", message)
        self._add_event({"type": "session", "session_id": session_id, "time_s": time_s, "action": "limit",
                         "reason": reason, "message": message})

        def stop():
            try:
                self._stop(session_id)
                if self._set_note is not None:
                    self._set_note(session_id, message)
            except Exception as exc:  # stopped meanwhile by a client: nothing left to do
                log.info("limit stop of %s: %s", session_id, exc)

        threading.Thread(target=stop, name="fc-limit-stop", daemon=True).start()
