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
    """Append-only writer; `write` buffers, `flush` hands the bytes to the OS (survives a process kill).

    A write that fails (a full disk) ends the log: `error` holds why, the file is cut back to its last
    whole record, and later frames are not written; the caller stops the session (server/limits.py)."""

    def __init__(self, path: str | Path, names: list[str], rate_hz: float | None, flush_s: float = 0.25):
        self.path = Path(path)
        self.m = len(names)
        self.dtype = record_dtype(self.m)
        self.flush_s = flush_s
        self.error: OSError | None = None
        self._fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        header = (json.dumps({"format": MAGIC, "version": 1, "names": list(names), "rate_hz": rate_hz}) + "\n").encode()
        try:
            _write_all(self._fd, header)
        except OSError:
            os.close(self._fd)
            self.path.unlink(missing_ok=True)
            raise
        self._whole = len(header)  # file size up to the last whole record written
        self._pending: list[bytes] = []
        self.last_flush = time.monotonic()
        self.frames = 0

    def write(self, times, rotations, positions, valid) -> None:
        if self._fd is None:  # ended (a failed write, or closed): the frames still reach the live fit
            return
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
            try:
                _write_all(self._fd, data)
                self._whole += len(data)
            except OSError as exc:
                self._fail(exc)
        elif self._fd is None:
            self._pending.clear()
        self.last_flush = time.monotonic()

    def _fail(self, exc: OSError) -> None:
        """Stop logging: keep the whole records written so far, readable as they are."""
        self.error = exc
        try:
            os.ftruncate(self._fd, self._whole)  # frees space; a partial record would only be skipped anyway
        except OSError:
            pass
        os.close(self._fd)
        self._fd = None

    def close(self) -> None:
        if self._fd is None:
            return
        self.flush()
        if self._fd is None:  # the last flush failed and closed it
            return
        try:
            os.fsync(self._fd)
        except OSError as exc:
            self.error = self.error or exc
        os.close(self._fd)
        self._fd = None


def _write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view):]


class FrameLogError(ValueError):
    """A frame log that cannot be read at all (its header is cut or damaged)."""


def parse_header(line: bytes, name: str) -> dict:
    """The frame log's JSON header line as a dict with a list of sensor names; FrameLogError otherwise."""
    if not line.endswith(b"\n"):
        raise FrameLogError(f"{name}: not a whole flockcal frame log (its header is cut short)")
    try:
        header = json.loads(line)
    except ValueError:
        raise FrameLogError(f"{name}: not a flockcal frame log (bad header)") from None
    if not isinstance(header, dict) or header.get("format") != MAGIC:
        raise FrameLogError(f"{name}: not a flockcal frame log")
    names = header.get("names")
    if not isinstance(names, list) or not names or not all(isinstance(x, str) for x in names):
        raise FrameLogError(f"{name}: the frame log's header names no sensors")
    rate = header.get("rate_hz")
    if rate is not None and (isinstance(rate, bool) or not isinstance(rate, (int, float)) or not 0 < rate < 1e5):
        header["rate_hz"] = None  # the mean rate of the arrivals is used instead
    return header


# A damaged record (bytes overwritten on disk) must not reach a fit or a download as a pose.
MAX_POSITION_M = 100.0
ROTATION_TOL = 1e-6  # stored rotations are projected onto SO(3) when decoded: orthonormal to ~1e-15


def time_span(first: np.ndarray, last: np.ndarray) -> tuple[float, float]:
    """(earliest, latest) plausible record time of a log, from records at its start and at its end."""
    lo = first[np.isfinite(first)]
    hi = last[np.isfinite(last)]
    if not len(lo) or not len(hi) or lo[0] > hi[-1]:
        return -np.inf, np.inf
    return float(lo[0]), float(hi[-1])


def sanitize(rec: np.ndarray, span: tuple[float, float], last_time: float) -> tuple:
    """Records (a frame log's dtype) as (times, rotations, positions, valid, the last time): a record whose
    time is not finite, outside the log's `span` or going back (before `last_time` or an earlier record), or
    whose valid flags are not 0/1, is damaged: it keeps the time before it and no valid sensor. A sensor
    whose rotation is not a rotation, or whose position is not finite or beyond MAX_POSITION_M, is invalid."""
    times = rec["time"].astype(float)
    flags = rec["valid"]
    R, p = rec["rot"], rec["pos"]
    ok = np.isfinite(times) & (times >= span[0]) & (times <= span[1])
    prev = np.maximum.accumulate(np.concatenate([[last_time], np.where(ok, times, -np.inf)]))[:-1]
    ok &= times >= prev
    ok &= (flags <= 1).all(axis=1)
    floor = np.where(np.isfinite(prev), prev, span[0] if np.isfinite(span[0]) else 0.0)
    times = np.where(ok, times, floor)
    with np.errstate(invalid="ignore", over="ignore"):
        gram = np.einsum("nmji,nmjk->nmik", R, R)
        rotation = (np.abs(gram - np.eye(3)) <= ROTATION_TOL).all(axis=(-1, -2))
        rotation &= np.linalg.det(np.where(np.isfinite(R), R, 0.0)) > 0
        place = np.isfinite(p).all(axis=-1) & (np.abs(p) <= MAX_POSITION_M).all(axis=-1)
    valid = (flags == 1) & ok[:, None] & rotation & place
    R = np.where(valid[..., None, None], R, 0.0)
    p = np.where(valid[..., None], p, 0.0)
    return times, R, p, valid, (float(times[-1]) if len(times) else last_time)


def read_frames(path: str | Path) -> dict:
    """Read a frame log: dict(names, rate_hz, times (n,), rotations (n,m,3,3), positions (n,m,3), valid (n,m)).
    Damaged records are kept as frames with no valid sensor (`sanitize`); FrameLogError when the log has
    no readable header."""
    path = Path(path)
    with open(path, "rb") as fh:
        header = parse_header(fh.readline(), path.name)
        body = fh.read()
    m = len(header["names"])
    dt = record_dtype(m)
    n = len(body) // dt.itemsize
    rec = np.frombuffer(body[: n * dt.itemsize], dtype=dt)
    span = time_span(rec["time"][:100], rec["time"][-100:])
    times, R, p, valid, _ = sanitize(rec, span, -np.inf)
    return {
        "names": header["names"],
        "rate_hz": header.get("rate_hz"),
        "times": times,
        "rotations": R,
        "positions": p,
        "valid": valid,
    }
