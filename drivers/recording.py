"""The `.fobraw` raw recording: every byte read from (and written to) the tracker, with arrival times.

A recording survives a crash: chunks are appended and flushed every few tens of milliseconds, each
with its own CRC, so a file cut short by kill -9 reads back up to the last flush; replay decodes the
same bytes through the same code path as the live read (`flockcal.drivers.assembly`).

File layout (all integers little-endian):

    magic     8 bytes  b"FOBRAW\\x00\\x01"  (format version 1)
    hlen      uint32   length of the settings JSON
    settings  hlen bytes of UTF-8 JSON (the TrackerConfig used, software version, start times)
    hcrc      uint32   CRC-32 of the settings JSON
    chunks    repeated until the end of the file:
        sync   2 bytes b"CK"
        kind   1 byte  b"R" bytes read, b"W" bytes written, b"M" a marker (UTF-8 JSON payload)
        port   uint8   index of the serial port (0 for group mode)
        time   float64 arrival time, time.monotonic() seconds of the recording process
        length uint32  payload length
        payload
        crc    uint32  CRC-32 of the 16 header bytes and the payload
"""

from __future__ import annotations

import json
import math
import os
import struct
import threading
import time
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import numpy as np

from flockcal.drivers.assembly import FrameAssembler  # the decoding path of the live reader
from flockcal.drivers.link import FlockSetup
from flockcal.drivers.records import record_length
from flockcal.errors import FlockcalError
from flockcal.frames import Frames

MAGIC = b"FOBRAW\x00\x01"
SYNC = b"CK"
READ, WRITE, MARK = b"R", b"W", b"M"
_CHUNK = struct.Struct("<2sccdI")
_U32 = struct.Struct("<I")
PROGRESS_CHUNKS = 2048  # replay reports its progress this often
MAX_CHUNK = 1 << 24  # no single read is this large; a bigger length means a damaged header


class RecordingError(FlockcalError):
    """A .fobraw file that cannot be written or read (missing, not a recording, or corrupt)."""


@dataclass(frozen=True)
class Chunk:
    """One piece of a recording: bytes read or written on one port, or a JSON marker."""

    kind: bytes  # READ, WRITE or MARK
    port: int
    time: float
    payload: bytes

    def marker(self) -> dict:
        return json.loads(self.payload.decode("utf-8"))


class RecordingWriter:
    """Appends chunks to a .fobraw file; safe to call from several threads.

    Chunks are buffered in memory and written out at most `flush_interval` seconds after they came
    in (and on `flush()`/`close()`), so a killed process loses at most that much.

    With `pending=True` the file is written beside its name (`NAME.part`) until `commit()` renames it
    into place, and `close()` before a commit removes it: a recording whose tracker never started
    leaves nothing behind and does not replace an earlier file of that name.
    """

    def __init__(self, path: str | os.PathLike, settings: dict, flush_interval: float = 0.05,
                 pending: bool = False):
        self.path = Path(path)
        self.pending = bool(pending)
        self._file = self.path.with_name(self.path.name + ".part") if pending else self.path
        self.flush_interval = float(flush_interval)
        head = dict(settings)
        head.setdefault("wall_start", time.strftime("%Y-%m-%dT%H:%M:%S%z"))
        head.setdefault("monotonic_start", time.monotonic())
        text = json.dumps(head, sort_keys=True, default=str).encode("utf-8")
        try:
            self._fh = open(self._file, "wb")
        except OSError as exc:
            raise RecordingError(f"cannot create the recording {self.path}: {exc.strerror} — check the folder exists and is writable") from None
        try:
            self._fh.write(MAGIC + _U32.pack(len(text)) + text + _U32.pack(zlib.crc32(text)))
            self._fh.flush()
        except OSError as exc:
            try:
                self._fh.close()
            except OSError:
                pass
            self._file.unlink(missing_ok=True)
            raise RecordingError(f"cannot write the recording {self.path}: {exc.strerror}") from None
        self._buf = bytearray()
        self._lock = threading.Lock()
        self._last_flush = time.monotonic()
        self.bytes_read = 0
        self.chunks = 0
        self.closed = False
        # A write that failed (a full disk): the recording ended there, whole up to its last flush (each
        # chunk has its CRC, so a cut one is skipped when read); the tracker is read on regardless.
        self.error: OSError | None = None

    def _append(self, kind: bytes, port: int, t: float, payload: bytes) -> None:
        head = _CHUNK.pack(SYNC, kind, bytes((port,)), t, len(payload))
        crc = zlib.crc32(payload, zlib.crc32(head))
        with self._lock:
            if self.closed:
                return
            self._buf += head
            self._buf += payload
            self._buf += _U32.pack(crc)
            self.chunks += 1
            if kind == READ:
                self.bytes_read += len(payload)
            if t - self._last_flush >= self.flush_interval:
                self._flush_locked(t)

    def read(self, t: float, port: int, data: bytes) -> None:
        """Log bytes that arrived on `port` at monotonic time `t`."""
        if data:
            self._append(READ, port, t, bytes(data))

    def wrote(self, t: float, port: int, data: bytes) -> None:
        """Log bytes sent to the tracker (commands); replay ignores them, they help diagnose a take."""
        if data:
            self._append(WRITE, port, t, bytes(data))

    def mark(self, t: float, info: dict) -> None:
        """Log a marker: a change of decoding state (stream start with its settings, reconnect, …)."""
        self._append(MARK, 0, t, json.dumps(info, sort_keys=True, default=str).encode("utf-8"))

    def _flush_locked(self, now: float) -> None:
        try:
            if self._buf:
                self._fh.write(self._buf)
                self._buf.clear()
            self._fh.flush()
        except OSError as exc:
            self._buf.clear()
            self.error, self.closed = exc, True
            try:
                self._fh.close()  # its buffer cannot be written either; close() may say so again
            except OSError:
                pass
        self._last_flush = now

    def flush(self) -> None:
        with self._lock:
            if not self.closed:
                self._flush_locked(time.monotonic())

    def commit(self) -> None:
        """Put a pending recording under its name (the tracker started: it is worth keeping)."""
        with self._lock:
            if self.pending and not self.closed:
                os.replace(self._file, self.path)
                self._file = self.path
                self.pending = False

    def close(self) -> None:
        with self._lock:
            if self.closed:
                return
            self.closed = True
            if self.pending:  # never committed: nothing worth keeping
                try:
                    self._fh.close()
                except OSError:
                    pass
                self._file.unlink(missing_ok=True)
                return
            self._flush_locked(time.monotonic())
            if self.error is not None:  # the flush failed and closed the file
                return
            try:
                os.fsync(self._fh.fileno())
            except OSError:
                pass
            try:
                self._fh.close()
            except OSError as exc:
                self.error = exc

    def __enter__(self) -> "RecordingWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


@dataclass
class Recording:
    """A recording read back: its settings, its chunks, and how much of a damaged tail was lost."""

    path: Path
    settings: dict
    chunks: list[Chunk]
    size: int  # bytes in the file
    good_bytes: int  # bytes up to the end of the last intact chunk
    problem: str | None = None  # why reading stopped early (truncated tail or corruption), if it did
    markers: list[dict] = field(default_factory=list)
    offsets: list[int] = field(default_factory=list)  # byte offset of each chunk in the file

    @property
    def truncated(self) -> bool:
        return self.good_bytes < self.size

    @property
    def bytes_read(self) -> int:
        return sum(len(c.payload) for c in self.chunks if c.kind == READ)

    @property
    def duration(self) -> float:
        times = [c.time for c in self.chunks]
        return (max(times) - min(times)) if times else 0.0

    def summary(self) -> str:
        """One line a person reads after replay: how much was recovered and why any was lost."""
        text = (
            f"{self.path.name}: {len(self.chunks)} chunks, {self.bytes_read} bytes read from the tracker "
            f"over {self.duration:.2f} s"
        )
        if self.truncated:
            text += f"; recovered {self.good_bytes} of {self.size} bytes ({self.problem})"
        return text


class ChunkReader:
    """A .fobraw file read a chunk at a time, memory a read block and one chunk: the settings header when
    opened (RecordingError if it is not a recording), then iterating gives (byte offset, Chunk) in file
    order. A tail cut short ends the chunks (`problem` says how); a damaged chunk with data after it is a
    RecordingError when reached, unless `salvage` ends the chunks there. Afterwards `good_bytes` is where
    the intact chunks end."""

    BLOCK = 1 << 20

    def __init__(self, path: str | os.PathLike, salvage: bool = False):
        self.path = Path(path)
        self.salvage = salvage
        try:
            self._fh = open(self.path, "rb")
        except FileNotFoundError:
            raise RecordingError(f"{self.path}: no such recording") from None
        except OSError as exc:
            raise RecordingError(f"{self.path}: cannot read it ({exc.strerror})") from None
        try:
            self.size = os.fstat(self._fh.fileno()).st_size
            self.settings, self.first = self._header()
        except BaseException:
            self._fh.close()
            raise
        self.problem: str | None = None
        self.good_bytes = self.size
        self.count = 0

    def _header(self) -> tuple[dict, int]:
        path = self.path
        head = self._fh.read(len(MAGIC) + 4)
        if not head.startswith(MAGIC):
            if head.startswith(MAGIC[:6]):
                raise RecordingError(f"{path}: a .fobraw recording of an unknown version — it needs a newer flockcal")
            raise RecordingError(f"{path}: not a flockcal raw recording (.fobraw) — it does not start with {MAGIC[:6]!r}")
        if len(head) < len(MAGIC) + 4:
            raise RecordingError(f"{path}: the recording is cut off inside its header; nothing can be recovered")
        (hlen,) = _U32.unpack_from(head, len(MAGIC))
        if hlen > MAX_CHUNK or self.size < len(head) + hlen + 4:
            raise RecordingError(f"{path}: the recording is cut off inside its header; nothing can be recovered")
        body = self._fh.read(hlen + 4)
        text = body[:hlen]
        if zlib.crc32(text) != _U32.unpack_from(body, hlen)[0]:
            raise RecordingError(f"{path}: the settings header is corrupt (checksum mismatch); the file cannot be replayed")
        try:
            settings = json.loads(text.decode("utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise RecordingError(f"{path}: the settings header is not valid JSON ({exc})") from None
        return settings, len(head) + hlen + 4

    def __iter__(self) -> Iterator[tuple[int, Chunk]]:
        buf, start = bytearray(), self.first  # buf holds the file from byte `start` on
        pos, size = self.first, self.size

        def have(upto: int) -> None:
            nonlocal buf, start
            if upto - start <= len(buf):
                return
            del buf[: pos - start]
            start = pos
            self._fh.seek(start + len(buf))
            buf += self._fh.read(max(upto - start - len(buf), self.BLOCK))

        try:
            while pos < size:
                if size - pos < _CHUNK.size:
                    self.problem = f"{size - pos} bytes of a chunk header cut off at the end"
                    break
                have(pos + _CHUNK.size)
                sync, kind, port, t, length = _CHUNK.unpack_from(buf, pos - start)
                end = pos + _CHUNK.size + length + 4
                damaged = sync != SYNC or kind not in (READ, WRITE, MARK) or length > MAX_CHUNK
                if not damaged and end > size:
                    self.problem = f"last chunk cut off ({size - pos} of {end - pos} bytes present)"
                    break
                if not damaged:
                    have(end)
                    at = pos - start
                    payload = bytes(buf[at + _CHUNK.size : at + _CHUNK.size + length])
                    (crc,) = _U32.unpack_from(buf, at + _CHUNK.size + length)
                    damaged = zlib.crc32(payload, zlib.crc32(buf[at : at + _CHUNK.size])) != crc
                if damaged:
                    self.problem = f"corrupt chunk at byte {pos} (chunk {self.count})"
                    if not self.salvage:
                        raise RecordingError(
                            f"{self.path}: {self.problem}, with {size - pos} bytes after it; the first {self.count} "
                            f"chunks are intact — replay them with --salvage"
                        )
                    break
                yield pos, Chunk(kind, port[0], t, payload)
                self.count += 1
                pos = end
        finally:
            self.good_bytes = pos if self.problem else size
            self._fh.close()


def read_recording(path: str | os.PathLike, salvage: bool = False) -> Recording:
    """Read a .fobraw file whole (ChunkReader's chunks in a list; a long one: `decode_recording`).

    A tail cut short (the process was killed mid-write) is dropped and noted in `problem`. A damaged
    chunk with intact data after it is corruption: a RecordingError, unless `salvage` keeps what came
    before it.
    """
    reader = ChunkReader(path, salvage)
    chunks, offsets, markers = [], [], []
    for pos, chunk in reader:
        chunks.append(chunk)
        offsets.append(pos)
        if chunk.kind == MARK and isinstance(info := _marker(chunk), dict):
            markers.append(info)
    return Recording(reader.path, reader.settings, chunks, reader.size, reader.good_bytes, reader.problem, markers,
                     offsets)


def _marker(chunk: Chunk):
    """A marker's JSON (None when its payload is not JSON: a junk chunk)."""
    try:
        return chunk.marker()
    except (UnicodeDecodeError, json.JSONDecodeError):
        return None


def intact_length(path: str | os.PathLike, size: int | None = None) -> int:
    """Bytes of the recording at `path`, among its first `size` (default: all it holds now), up to the end
    of its last whole chunk: what a copy of a recording still being written can take and be a whole
    recording (the writer appends whole chunks, but a reader can see the file between two writes).

    Read backwards from `size`, a window at a time: the last place where a chunk header and its CRC
    check out, with the chunk ending within `size`, is the last whole chunk (the writer only appends).
    Returns 0 while the header itself is incomplete."""
    with open(path, "rb") as fh:
        size = os.fstat(fh.fileno()).st_size if size is None else int(size)
        head = fh.read(len(MAGIC) + 4)
        if len(head) < len(MAGIC) + 4 or not head.startswith(MAGIC):
            return 0
        (hlen,) = _U32.unpack_from(head, len(MAGIC))
        first = len(MAGIC) + 4 + hlen + 4  # where the chunks begin
        if size < first:
            return 0
        window = 1 << 16
        hi = size
        while hi > first:
            lo = max(first, hi - window)
            fh.seek(lo)
            data = fh.read(hi + len(SYNC) - 1 - lo)  # a sync straddling `hi` is looked at in this window
            at = data.rfind(SYNC)
            while at >= 0:
                end = _whole_chunk_end(fh, lo + at, size)
                if end is not None:
                    return end
                at = data.rfind(SYNC, 0, at)
            hi = lo
            window *= 2
        return first


def _whole_chunk_end(fh, pos: int, size: int) -> int | None:
    """The end of the chunk starting at `pos` when it is whole within `size` bytes and its CRC holds."""
    if pos + _CHUNK.size + 4 > size:
        return None
    fh.seek(pos)
    head = fh.read(_CHUNK.size)
    sync, kind, _port, _t, length = _CHUNK.unpack(head)
    end = pos + _CHUNK.size + length + 4
    if sync != SYNC or kind not in (READ, WRITE, MARK) or length > MAX_CHUNK or end > size:
        return None
    body = fh.read(length + 4)
    if len(body) < length + 4:
        return None
    (crc,) = _U32.unpack_from(body, length)
    return end if zlib.crc32(body[:length], zlib.crc32(head)) == crc else None


@dataclass
class Junk:
    """Chunks whose checksums hold but that no recorder wrote (random or foreign data spliced in), all
    skipped: where they are and why each was judged so (a time out of the recording's order, a port it does
    not have, a marker that is not a recorder's JSON, read bytes with more phasing bits than Flock records
    can hold)."""

    chunks: int = 0
    bytes: int = 0
    first: int | None = None  # byte offset of the first such chunk
    end: int | None = None  # where the last one ends
    reasons: dict = field(default_factory=dict)  # reason → chunks

    def add(self, pos: int | None, end: int | None, size: int, reason: str) -> None:
        self.chunks += 1
        self.bytes += size
        self.reasons[reason] = self.reasons.get(reason, 0) + 1
        if pos is not None:
            self.first = pos if self.first is None else min(self.first, pos)
            self.end = end if self.end is None else max(self.end, end)

    def __bool__(self) -> bool:
        return self.chunks > 0

    def describe(self) -> str:
        where = f" between bytes {self.first:,} and {self.end:,}" if self.first is not None else ""
        why = "; ".join(f"{n:,} {reason}" for reason, n in sorted(self.reasons.items(), key=lambda x: -x[1]))
        return f"{self.chunks:,} junk chunk{'s' if self.chunks != 1 else ''} ({self.bytes:,} bytes){where}: {why}"


# A chunk's time may run behind the one before it by this much (a marker from another thread stamped a
# moment earlier), and ahead by this much (a stalled process); anything else was not stamped by a recorder.
BACKWARD_S = 1.0
FORWARD_S = 86400.0


@dataclass
class Replay:
    """What replaying a recording gave: the frames, the decoding settings, events and counters."""

    frames: Frames
    setups: list[dict]
    events: list[dict]
    sessions: int
    resyncs: int
    dropped_records: int
    rejected_records: int
    junk: Junk = field(default_factory=Junk)
    frame_count: int = 0  # frames decoded (all of them, also when they were handed on and not kept)


class Decoder:
    """A recording's chunks → frames through the live reader's assembler, one chunk at a time (replay's
    engine): markers start and end streams, read bytes are fed with their arrival times, junk chunks are
    judged (`Junk`) and kept out of the assembler where they would corrupt it. `on_frames(frames)` gets the
    frames in batches; with `keep` they are also kept for `result()`."""

    def __init__(self, settings: dict, on_frames=None, *, keep: bool = True, realtime: bool = False,
                 speed: float = 1.0, batch_seconds: float = 0.05):
        self.on_frames, self.keep = on_frames, keep
        self.realtime, self.speed, self.batch_seconds = realtime, speed, batch_seconds
        self.parts: list[Frames] = []
        self.setups: list[dict] = []
        self.events: list[dict] = []
        self.junk = Junk()
        self.frames = 0
        self.m = 0
        self.asm: FrameAssembler | None = None
        self.totals = dict(resyncs=0, dropped=0, rejected=0)
        config = settings.get("config") if isinstance(settings.get("config"), dict) else {}
        urls = config.get("urls")
        self.ports = len(urls) if isinstance(urls, list) and urls else 256  # until a stream says
        start = settings.get("monotonic_start")
        self.latest = float(start) if isinstance(start, (int, float)) and math.isfinite(start) else None
        self.record_bytes = 0
        self.wall0 = time.monotonic()
        self.rec0: float | None = None
        self.last_emit = 0.0

    def feed(self, chunk: Chunk, pos: int | None = None, end: int | None = None) -> None:
        t = chunk.time
        reason = None
        if not math.isfinite(t) or (self.latest is not None and not
                                    self.latest - BACKWARD_S <= t <= self.latest + FORWARD_S):
            reason = "with times no recorder wrote"
        elif chunk.kind != MARK and chunk.port >= self.ports:
            reason = f"on ports the recording does not have (it has {self.ports})"
        elif chunk.kind == MARK:
            info = _marker(chunk)
            if not isinstance(info, dict) or ("stream" in info and not self._stream(info, t)):
                reason = "markers that are not a recorder's"
        if reason is not None:
            self.junk.add(pos, end, len(chunk.payload), reason)
            return
        self.latest = t if self.latest is None else max(self.latest, t)
        if self.rec0 is None:
            self.rec0 = self.last_emit = t
        if chunk.kind == MARK:
            if info.get("flush"):
                self._collect(t, force=True)
                self._retire()
            elif "event" in info:
                self.events.append(info)
        elif chunk.kind == READ and self.asm is not None:
            if self._not_records(chunk.payload):
                self.junk.add(pos, end, len(chunk.payload), "of bytes that cannot be Flock records")
                return
            self.asm.feed(chunk.port, t, chunk.payload)
            self._collect(t)

    def _stream(self, info: dict, t: float) -> bool:
        """Start decoding the stream a marker describes; False when it describes none a recorder makes."""
        try:
            setup = FlockSetup.from_dict(info["stream"])
            asm = FrameAssembler(setup, **info.get("assembler", {}))
        except (TypeError, ValueError, KeyError, AttributeError, IndexError):
            return False
        self._retire()
        self.setups.append(info["stream"])
        self.m = setup.birds
        self.asm = asm
        self.ports = len(asm.ports) if setup.group else len(setup.urls)
        self.record_bytes = record_length(setup.record_format, group=setup.group)
        self.last_emit = t
        return True

    def _not_records(self, data: bytes) -> bool:
        """Whether read bytes cannot be a Flock stream: its records carry one phasing byte (high bit set) in
        `record_bytes`, so a stretch of several records holds few; random bytes hold one in two."""
        n, L = len(data), self.record_bytes
        if n < 4 * L:
            return False
        high = int(np.count_nonzero(np.frombuffer(data, np.uint8) & 0x80))
        return high > 2 * n / L + 2

    def _collect(self, now: float, force: bool = False) -> None:
        if self.asm is None or (not force and now - self.last_emit < self.batch_seconds):
            return
        self.last_emit = now
        out = self.asm.take()
        if len(out):
            self.frames += len(out)
            if self.keep:
                self.parts.append(out)
            if self.on_frames is not None:
                if self.realtime:
                    delay = (now - self.rec0) / self.speed - (time.monotonic() - self.wall0)
                    if delay > 0:
                        time.sleep(delay)
                self.on_frames(out)

    def _retire(self) -> None:
        if self.asm is None:
            return
        self.asm.flush()
        self._collect(self.last_emit, force=True)
        self.totals["resyncs"] += self.asm.resyncs
        self.totals["dropped"] += self.asm.dropped_records
        self.totals["rejected"] += self.asm.rejected_records
        self.asm = None

    def finish(self) -> Replay:
        """End the last stream; what the replay gave (its frames if kept, else none)."""
        self._retire()
        frames = Frames.concat(self.parts, self.m)
        return Replay(frames, self.setups, self.events, len(self.setups), self.totals["resyncs"],
                      self.totals["dropped"], self.totals["rejected"], self.junk, self.frames)


def replay(recording: Recording, on_frames=None, realtime: bool = False, speed: float = 1.0,
           batch_seconds: float = 0.05, on_progress=None) -> Replay:
    """Decode a recording through the same assembler as the live read (same bytes, same order, same
    arrival times), so the frames are identical to the ones the live reader delivered.

    `on_frames(frames)` is called with `Frames` in batches; with `realtime` the batches
    are paced by the recorded arrival times (divided by `speed`). `on_progress(chunks done)` is called
    every PROGRESS_CHUNKS chunks and at the end (for a progress bar). Junk chunks (`Replay.junk`) are
    counted, and kept out of the assembler where they would corrupt it.
    """
    dec = Decoder(recording.settings, on_frames, realtime=realtime, speed=speed, batch_seconds=batch_seconds)
    offsets = recording.offsets or [None] * len(recording.chunks)
    for k, (chunk, pos) in enumerate(zip(recording.chunks, offsets)):
        if on_progress is not None and k % PROGRESS_CHUNKS == 0 and k:
            on_progress(k)
        end = None if pos is None else pos + _CHUNK.size + len(chunk.payload) + 4
        dec.feed(chunk, pos, end)
    out = dec.finish()
    if on_progress is not None:
        on_progress(len(recording.chunks))
    return out


def decode_recording(reader: ChunkReader, decoder: Decoder, on_progress=None) -> Replay:
    """Feed every chunk `reader` gives to `decoder` (one made with keep=False keeps no frames: memory is
    then a read block, one chunk and the assembler's state, whatever the file's length); its Replay.
    `on_progress(bytes done)` every PROGRESS_CHUNKS chunks and at the end."""
    for k, (pos, chunk) in enumerate(reader):
        decoder.feed(chunk, pos, pos + _CHUNK.size + len(chunk.payload) + 4)
        if on_progress is not None and k % PROGRESS_CHUNKS == 0 and k:
            on_progress(pos)
    out = decoder.finish()
    if on_progress is not None:
        on_progress(reader.size)
    return out
