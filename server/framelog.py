"""A session's received frames, appended to a file as they arrive and flushed several times a second.

Format: one JSON header line (`{"format": "flockcal-frames", "version": 2, "names": [...], "rate_hz": r}`)
then blocks of the frames of each flush (server/frameblocks.py: the tracker's words, deflated, each block
with its checksum), about 180 bytes a frame for 16 sensors. Version 1 (still read) held fixed-size
little-endian records instead: time f8, valid m×u1, rotations m×9 f8, positions m×3 f8 (1,560 bytes a
frame for 16). Either way a crash leaves at most a partial last block or record, which readers ignore;
so a kill -9 loses only what had not been flushed (≤ `flush_s`).
"""

from __future__ import annotations

import errno
import json
import logging
import os
import threading
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Iterator

import numpy as np

from flockcal.clock import SYSTEM, Clock
from flockcal.frames import Frames, TrackerWords
from flockcal.server.frameblocks import HEAD, SYNC, BlockError, Encoder, decode, parse_head, record_dtype, records_frames
from flockcal.threads import name_os_thread

log = logging.getLogger(__name__)

MAGIC = "flockcal-frames"
VERSION = 2
BLOCK_BYTES = 1 << 20  # a block decodes to at most this much (a reader holds a block at a time)

__all__ = ["FrameLog", "FrameLogError", "FrameLogReader", "Header", "parse_header", "read_frames", "record_dtype",
           "sanitize", "time_span"]


class FrameLog:
    """Append-only writer; `write` buffers (the first frames are written at once), `flush` hands the bytes
    to the OS (survives a process kill).

    The blocks are encoded and written on a thread of the log's own ("fc-framelog"): encoding a quarter
    second of frames takes milliseconds, which the pipeline thread, on the way from a frame to the clients'
    snapshots, would otherwise spend every quarter second. `write` and `flush(wait=False)` only hand a
    flush's frames over; `flush()` and `close()` return once everything handed over is written. Each flush's
    frames become their own blocks, in order, whatever thread encodes them.

    A write that fails (a full disk) ends the log: `error` holds why, the file is cut back to its last
    whole block, and later frames are not written; the caller stops the session (server/limits.py)."""

    def __init__(self, path: str | Path, names: list[str], rate_hz: float | None, flush_s: float = 0.25,
                 clock: Clock = SYSTEM):
        self.path = Path(path)
        self.m = len(names)
        self.dtype = record_dtype(self.m)
        self.flush_s = flush_s
        self.clock = clock  # the flush cadence
        self.error: OSError | None = None
        self._fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        header = (json.dumps({"format": MAGIC, "version": VERSION, "names": list(names), "rate_hz": rate_hz})
                  + "\n").encode()
        try:
            _write_all(self._fd, header)
        except OSError:
            os.close(self._fd)
            self.path.unlink(missing_ok=True)
            raise
        self._whole = len(header)  # file size up to the last whole block written
        self._pending: list[Frames] = []
        self._encoder = Encoder()
        self._block_frames = max(1, BLOCK_BYTES // self.dtype.itemsize)
        self.last_flush = clock.monotonic()
        self.frames = 0
        self._ended = False  # a write failed, or closed: later frames are not logged
        # The writer thread's hand-over: flushes' frames in order, how many were handed over and written.
        self._cond = threading.Condition()
        self._queue: list[list[Frames]] = []
        self._handed = self._written = 0
        self._closing = False
        self._thread: threading.Thread | None = None

    def write(self, times, rotations, positions, valid, words: TrackerWords | None = None) -> None:
        """Log n frames; `words`, the tracker's data words they were decoded from where they came from a
        tracker (Frames.words), are stored as they are instead of being worked out again from the floats."""
        if self._ended:  # a failed write, or closed: the frames still reach the live fit
            return
        n = len(times)
        # Copies: the caller's arrays may be reused before the flush.
        self._pending.append(Frames(np.array(times, "<f8"), np.array(rotations, float), np.array(positions, float),
                                    np.array(valid, bool),
                                    None if words is None else replace(words, words=np.array(words.words))))
        self.frames += n
        # The first frames go out at once: a fit of them is published within a frame or two (fits run at
        # 30 Hz), and a download or the rig a page loads for it must find the session's log holding frames.
        if n and self.frames == n:
            self.flush()
        elif self.clock.monotonic() - self.last_flush >= self.flush_s:
            self.flush(wait=False)

    def flush(self, wait: bool = True) -> None:
        """Hand the frames written since the last flush to the writer thread; with `wait`, return once
        they (and all before them) are in the file, or the log has ended."""
        self.last_flush = self.clock.monotonic()
        with self._cond:
            if self._pending and not self._ended:
                self._queue.append(self._pending)
                self._handed += 1
                if self._thread is None:
                    self._thread = threading.Thread(target=self._run, name="flockcal-framelog", daemon=True)
                    self._thread.start()
                self._cond.notify_all()
            self._pending = []
        if wait:
            self.wait_written()

    def wait_written(self) -> None:
        """Return once every flush handed over so far is in the file (or the log has ended)."""
        with self._cond:
            target = self._handed
            while self._written < target and not self._ended:
                self._cond.wait()

    def _run(self) -> None:
        name_os_thread("fc-framelog")
        while True:
            with self._cond:
                while not self._queue and not self._closing:
                    self._cond.wait()
                if not self._queue:
                    return
                batches = self._queue.pop(0)
            try:
                self._write_blocks(batches)
            except Exception as exc:  # noqa: BLE001 -- not a disk's error: the log ends as on one, said why
                log.exception("frame log %s: encoding failed; the recording stops here", self.path.name)
                self._fail(OSError(errno.EIO, f"encoding the frames failed ({type(exc).__name__}: {exc})"))
            with self._cond:
                self._written += 1
                self._cond.notify_all()

    def _write_blocks(self, batches: list[Frames]) -> None:
        if self._fd is None:
            return
        frames = Frames.concat(batches, self.m)
        step = self._block_frames
        data = b"".join(self._encoder.block(f.times, f.rotations, f.positions, f.valid, f.words)
                        for f in (frames[a:a + step] for a in range(0, len(frames), step)))
        try:
            _write_all(self._fd, data)
            self._whole += len(data)
        except OSError as exc:
            self._fail(exc)

    def _fail(self, exc: OSError) -> None:
        """Stop logging: keep the whole records written so far, readable as they are (the writer thread)."""
        self.error = exc
        try:
            os.ftruncate(self._fd, self._whole)  # frees space; a partial record would only be skipped anyway
        except OSError:
            pass
        os.close(self._fd)
        self._fd = None
        with self._cond:
            self._ended = True
            self._queue.clear()
            self._cond.notify_all()

    def close(self) -> None:
        """Write what is pending, stop the writer thread, and close the file (synced to the disk)."""
        if self._ended and self._thread is None and self._fd is None:
            return
        self.flush()
        with self._cond:
            self._ended = self._closing = True
            self._cond.notify_all()
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        if self._fd is None:  # a flush failed and closed it
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


@dataclass(frozen=True)
class Header:
    """A frame log's header line: the sensors' names, the tracker's rate (None: unknown or implausible, the
    mean rate of the arrivals is used instead) and the format's version (1 or 2)."""

    names: tuple[str, ...]
    rate_hz: float | None
    version: int


def parse_header(line: bytes, name: str) -> Header:
    """The frame log's JSON header line; FrameLogError when it is not one this flockcal reads."""
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
    version = header.get("version", 1)
    if version not in (1, VERSION):
        raise FrameLogError(f"{name}: a frame log of version {version!r}, which this flockcal does not read "
                            f"(it reads versions 1 and {VERSION}); read it with the flockcal that wrote it")
    rate = header.get("rate_hz")
    if rate is not None and (isinstance(rate, bool) or not isinstance(rate, (int, float)) or not 0 < rate < 1e5):
        rate = None
    return Header(tuple(names), rate, version)


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


def sanitize(raw: Frames, span: tuple[float, float], last_time: float) -> tuple[Frames, float]:
    """Frames as stored (`valid` the stored flags) as frames to use, and the last time: a record whose
    time is not finite, outside the log's `span` or going back (before `last_time` or an earlier record), or
    whose valid flags are not 0/1, is damaged: it keeps the time before it and no valid sensor. A sensor
    whose rotation is not a rotation, or whose position is not finite or beyond MAX_POSITION_M, is invalid."""
    times = raw.times.astype(float)
    flags = raw.valid
    R, p = raw.rotations, raw.positions
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
    return Frames(times, R, p, valid), (float(times[-1]) if len(times) else last_time)


class FrameLogReader:
    """A frame log opened for reading: `header`, `names`, `rate_hz`, `version`, `n` whole frames (fixed at
    open: a live session's log grows on), and its frames as stored (`frameblocks.records_frames`: not yet
    `sanitize`d) read by range or in turn.

    The file stays open until `close()` (or the end of a `with`): what is read is what was opened, whatever
    happens to its name meanwhile. A block whose bytes are damaged reads as records with no time and no valid
    sensor (`sanitize` makes them frames with no valid sensor); one whose head is damaged is skipped to the
    next whole block."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self._fh = open(self.path, "rb")
        try:
            self._open()
        except BaseException:
            self._fh.close()
            raise

    def _open(self) -> None:
        line = self._fh.readline()
        self.offset = self._fh.tell()
        self.header = parse_header(line, self.path.name)  # FrameLogError (a ValueError) when cut or damaged
        self.names: list[str] = list(self.header.names)
        self.rate_hz = self.header.rate_hz
        self.version = self.header.version
        self.m = len(self.names)
        self.dtype = record_dtype(self.m)
        size = os.fstat(self._fh.fileno()).st_size
        if self.version == 1:
            self.n = (size - self.offset) // self.dtype.itemsize
        else:
            self._blocks = _block_index(self._fh.fileno(), self.offset, size)  # (offset, codec, frames, bytes, crc)
            counts = np.array([b[2] for b in self._blocks], dtype=np.int64)
            self._starts = np.concatenate([[0], np.cumsum(counts)])  # first frame of each block
            self.n = int(self._starts[-1])

    def close(self) -> None:
        self._fh.close()

    def __enter__(self) -> "FrameLogReader":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def frames(self, start: int, count: int) -> Frames:
        """Frames start … start + count (clipped to the log's n), as stored."""
        start, stop = max(0, start), min(self.n, start + count)
        if stop <= start:
            return Frames.empty(self.m)
        if self.version == 1:
            return self._frames_v1(start, stop - start)
        first = int(np.searchsorted(self._starts, start, side="right")) - 1
        last = int(np.searchsorted(self._starts, stop, side="left"))
        frames = Frames.concat([self._decode(k) for k in range(first, last)], self.m)
        a = start - int(self._starts[first])
        return frames[a:a + stop - start]

    def chunks(self, size: int) -> Iterator[Frames]:
        """All n frames as stored, `size` at a time (the last chunk shorter): memory stays a chunk and a block."""
        if self.version == 1:
            for start in range(0, self.n, size):
                frames = self._frames_v1(start, min(size, self.n - start))
                if not len(frames):
                    return
                yield frames
            return
        held: list[Frames] = []
        have = 0
        for k in range(len(self._blocks)):
            held.append(self._decode(k))
            have += len(held[-1])
            while have >= size:
                frames = Frames.concat(held, self.m)
                yield frames[:size]
                held, have = [frames[size:]], have - size
        if have:
            yield Frames.concat(held, self.m)

    def _frames_v1(self, start: int, count: int) -> Frames:
        size = self.dtype.itemsize
        data = os.pread(self._fh.fileno(), count * size, self.offset + start * size)
        return records_frames(np.frombuffer(data, dtype=self.dtype, count=len(data) // size))

    def _decode(self, k: int) -> Frames:
        offset, codec, n, size, crc = self._blocks[k]
        try:
            return decode(codec, n, self.m, os.pread(self._fh.fileno(), size, offset + HEAD.size), crc)
        except BlockError:
            # No time and no valid sensor: `sanitize` makes them frames with no valid sensor.
            return Frames(np.full(n, np.nan), np.zeros((n, self.m, 3, 3)), np.zeros((n, self.m, 3)),
                          np.zeros((n, self.m), np.uint8))


def _block_index(fd: int, offset: int, size: int) -> list[tuple[int, int, int, int, int]]:
    """(offset, codec, frames, payload bytes, payload CRC) of each whole block of a version-2 log of `size`
    bytes; a damaged head is skipped to the next whole block, a block cut short by a crash ends the list."""
    out = []
    at = offset
    while at + HEAD.size <= size:
        head = parse_head(os.pread(fd, HEAD.size, at))
        if head is None:
            at = _next_head(fd, at + 1, size)
            continue
        codec, n, length, crc = head
        if at + HEAD.size + length > size:
            break
        out.append((at, codec, n, length, crc))
        at += HEAD.size + length
    return out


def _next_head(fd: int, at: int, size: int, step: int = 1 << 20) -> int:
    """Where the next whole block head lies from `at` on (`size` when there is none)."""
    while at + HEAD.size <= size:
        buf = os.pread(fd, step + HEAD.size, at)
        i = buf.find(SYNC)
        while i >= 0 and i + HEAD.size <= len(buf):
            head = parse_head(buf[i:i + HEAD.size])
            if head is not None and at + i + HEAD.size + head[2] <= size:
                return at + i
            i = buf.find(SYNC, i + 1)
        at += step
    return size


def read_frames(path: str | Path) -> tuple[Header, Frames]:
    """Read a whole frame log: its header and its frames. Damaged records are kept as frames with no valid
    sensor (`sanitize`); FrameLogError when the log has no readable header."""
    with FrameLogReader(path) as log:
        raw = log.frames(0, log.n)
    frames, _ = sanitize(raw, time_span(raw.times[:100], raw.times[-100:]), -np.inf)
    return log.header, frames
