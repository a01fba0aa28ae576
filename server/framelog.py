"""A session's received frames, appended to a file as they arrive and flushed several times a second.

Format: one JSON header line (`{"format": "flockcal-frames", "version": 1, "names": [...], "rate_hz": r}`)
then fixed-size little-endian records: time f8, valid m×u1, rotations m×9 f8, positions m×3 f8.
A crash leaves at most a partial last record, which `read_frames` ignores; so a kill -9 loses only
what had not been flushed (≤ `flush_s`).
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np

MAGIC = "flockcal-frames"


def record_dtype(m: int) -> np.dtype:
    return np.dtype([("time", "<f8"), ("valid", "u1", (m,)), ("rot", "<f8", (m, 3, 3)), ("pos", "<f8", (m, 3))])


class FrameLog:
    """Append-only writer; `write` buffers, `flush` hands the bytes to the OS (survives a process kill)."""

    def __init__(self, path: str | Path, names: list[str], rate_hz: float | None, flush_s: float = 0.25):
        self.path = Path(path)
        self.m = len(names)
        self.dtype = record_dtype(self.m)
        self.flush_s = flush_s
        self._fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        header = json.dumps({"format": MAGIC, "version": 1, "names": list(names), "rate_hz": rate_hz}) + "\n"
        os.write(self._fd, header.encode())
        self._pending: list[bytes] = []
        self.last_flush = time.monotonic()
        self.frames = 0

    def write(self, times, rotations, positions, valid) -> None:
        n = len(times)
        rec = np.empty(n, dtype=self.dtype)
        rec["time"] = times
        rec["valid"] = valid
        rec["rot"] = rotations
        rec["pos"] = positions
        self._pending.append(rec.tobytes())
        self.frames += n
        if time.monotonic() - self.last_flush >= self.flush_s:
            self.flush()

    def flush(self) -> None:
        if self._pending and self._fd is not None:
            data = b"".join(self._pending)
            self._pending.clear()
            view = memoryview(data)
            while view:
                view = view[os.write(self._fd, view):]
        self.last_flush = time.monotonic()

    def close(self) -> None:
        if self._fd is None:
            return
        self.flush()
        os.fsync(self._fd)
        os.close(self._fd)
        self._fd = None


def read_frames(path: str | Path) -> dict:
    """Read a frame log: dict(names, rate_hz, times (n,), rotations (n,m,3,3), positions (n,m,3), valid (n,m))."""
    path = Path(path)
    with open(path, "rb") as fh:
        header_line = fh.readline()
        try:
            header = json.loads(header_line)
        except ValueError:
            raise ValueError(f"{path.name}: not a flockcal frame log (bad header)") from None
        if header.get("format") != MAGIC:
            raise ValueError(f"{path.name}: not a flockcal frame log")
        body = fh.read()
    m = len(header["names"])
    dt = record_dtype(m)
    n = len(body) // dt.itemsize
    rec = np.frombuffer(body[: n * dt.itemsize], dtype=dt)
    return {
        "names": header["names"],
        "rate_hz": header.get("rate_hz"),
        "times": rec["time"].copy(),
        "rotations": rec["rot"].copy(),
        "positions": rec["pos"].copy(),
        "valid": rec["valid"].astype(bool),
    }
