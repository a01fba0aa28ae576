"""Per-session raw tracker bytes (.fobraw, drivers/recording.py) from a reader that runs for the
service's whole lifetime.

`SessionRawRecorder` sits in the reader's recorder slot once, for good, and forwards bytes to the live
session's RecordingWriter (or drops them between sessions). Each session file starts with the latest
stream-setup marker, so `flockcal replay/convert` can decode it like any recording.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

from flockcal import __version__


class SessionRawRecorder:
    def __init__(self, config: dict, names: list[str] | None = None):
        self.config = config
        self.names = list(names) if names else None  # kept in each file's header for replay and convert
        self._writer = None
        self._stream_marker: dict | None = None
        self._lock = threading.Lock()

    # The reader's recorder interface (called from its threads).
    def read(self, t: float, port: int, data: bytes) -> None:
        w = self._writer
        if w is not None:
            w.read(t, port, data)  # a writer closed meanwhile ignores the call

    def wrote(self, t: float, port: int, data: bytes) -> None:
        w = self._writer
        if w is not None:
            w.wrote(t, port, data)

    def mark(self, t: float, info: dict) -> None:
        if "stream" in info:
            self._stream_marker = dict(info)
        w = self._writer
        if w is not None:
            w.mark(t, info)

    def flush(self) -> None:
        w = self._writer
        if w is not None:
            w.flush()

    def commit(self) -> None:
        """Session files are written under their own names from the start."""

    def close(self) -> None:
        """The reader stopping does not end a session's file; `stop` does."""

    # Session control.
    def start(self, path: str | Path) -> None:
        from flockcal.drivers.recording import RecordingWriter

        header = {"flockcal": __version__, "config": self.config, "session_file": True}
        if self.names:
            header["names"] = self.names
        writer = RecordingWriter(path, header)
        if self._stream_marker is not None:
            writer.mark(time.monotonic(), self._stream_marker)
        with self._lock:
            old, self._writer = self._writer, writer
        if old is not None:
            old.close()

    def stop(self) -> None:
        with self._lock:
            old, self._writer = self._writer, None
        if old is not None:
            old.close()
