"""Holds on a session's files: a download in progress holds them, so a DELETE answers 409 (Retry-After) and
retention passes the session by until the download ends; a download that starts while they are being
removed answers as if they were gone already (404 deleted, 410 pruned), never a half-sent body or a 500.
"""

from __future__ import annotations

import threading
from collections import Counter
from typing import Callable

from flockcal.server.errors import ServerError

RETRY_AFTER_S = 5  # what a DELETE refused for a download in progress is told to wait


class FileHolds:
    """Downloads holding each session's files, and the sessions whose files are being removed."""

    def __init__(self):
        self._lock = threading.Lock()
        self._held: Counter[str] = Counter()
        self._removing: dict[str, Callable[[], ServerError]] = {}

    def hold(self, session_id: str) -> Callable[[], None]:
        """Hold the session's files for a download; returns the release (call it once, when it ends). Raises
        the remover's error while they are being removed."""
        with self._lock:
            gone = self._removing.get(session_id)
            if gone is not None:
                raise gone()
            self._held[session_id] += 1
        released = False

        def release() -> None:
            nonlocal released
            with self._lock:
                if released:
                    return
                released = True
                self._held[session_id] -= 1
                if self._held[session_id] <= 0:
                    del self._held[session_id]

        return release

    def held(self, session_id: str) -> int:
        with self._lock:
            return self._held.get(session_id, 0)

    def claim(self, session_id: str, gone: Callable[[], ServerError]) -> int:
        """Before removing the session's files: 0 and the files are the caller's (downloads starting meanwhile
        get `gone()`) until `unclaim`; else the number of downloads holding them, and nothing is claimed."""
        with self._lock:
            n = self._held.get(session_id, 0)
            if n == 0:
                self._removing[session_id] = gone
            return n

    def unclaim(self, session_id: str) -> None:
        with self._lock:
            self._removing.pop(session_id, None)
