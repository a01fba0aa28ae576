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
import os
import struct
import threading
import time
import zlib
from dataclasses import dataclass, field
from pathlib import Path

from flockcal.drivers.assembly import FrameAssembler  # the decoding path of the live reader
from flockcal.drivers.link import FlockSetup
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
        self._fh.write(MAGIC + _U32.pack(len(text)) + text + _U32.pack(zlib.crc32(text)))
        self._fh.flush()
        self._buf = bytearray()
        self._lock = threading.Lock()
        self._last_flush = time.monotonic()
        self.bytes_read = 0
        self.chunks = 0
        self.closed = False

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
        if self._buf:
            self._fh.write(self._buf)
            self._buf.clear()
        self._fh.flush()
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
                self._fh.close()
                self._file.unlink(missing_ok=True)
                return
            self._flush_locked(time.monotonic())
            try:
                os.fsync(self._fh.fileno())
            except OSError:
                pass
            self._fh.close()

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


def read_recording(path: str | os.PathLike, salvage: bool = False) -> Recording:
    """Read a .fobraw file.

    A tail cut short (the process was killed mid-write) is dropped and noted in `problem`. A damaged
    chunk with intact data after it is corruption: a RecordingError, unless `salvage` keeps what came
    before it.
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise RecordingError(f"{path}: no such recording") from None
    except OSError as exc:
        raise RecordingError(f"{path}: cannot read it ({exc.strerror})") from None
    if not data.startswith(MAGIC):
        if data.startswith(MAGIC[:6]):
            raise RecordingError(f"{path}: a .fobraw recording of an unknown version — it needs a newer flockcal")
        raise RecordingError(f"{path}: not a flockcal raw recording (.fobraw) — it does not start with {MAGIC[:6]!r}")
    pos = len(MAGIC)
    if len(data) < pos + 4:
        raise RecordingError(f"{path}: the recording is cut off inside its header; nothing can be recovered")
    (hlen,) = _U32.unpack_from(data, pos)
    pos += 4
    if len(data) < pos + hlen + 4:
        raise RecordingError(f"{path}: the recording is cut off inside its header; nothing can be recovered")
    text = data[pos : pos + hlen]
    (hcrc,) = _U32.unpack_from(data, pos + hlen)
    if zlib.crc32(text) != hcrc:
        raise RecordingError(f"{path}: the settings header is corrupt (checksum mismatch); the file cannot be replayed")
    try:
        settings = json.loads(text.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise RecordingError(f"{path}: the settings header is not valid JSON ({exc})") from None
    pos += hlen + 4

    chunks: list[Chunk] = []
    markers: list[dict] = []
    problem = None
    size = len(data)
    while pos < size:
        if size - pos < _CHUNK.size:
            problem = f"{size - pos} bytes of a chunk header cut off at the end"
            break
        sync, kind, port, t, length = _CHUNK.unpack_from(data, pos)
        end = pos + _CHUNK.size + length + 4
        damaged = sync != SYNC or kind not in (READ, WRITE, MARK) or length > MAX_CHUNK
        if not damaged and end > size:
            problem = f"last chunk cut off ({size - pos} of {end - pos} bytes present)"
            break
        if not damaged:
            payload = data[pos + _CHUNK.size : end - 4]
            (crc,) = _U32.unpack_from(data, end - 4)
            damaged = zlib.crc32(payload, zlib.crc32(data[pos : pos + _CHUNK.size])) != crc
        if damaged:
            problem = f"corrupt chunk at byte {pos} (chunk {len(chunks)})"
            if not salvage:
                raise RecordingError(
                    f"{path}: {problem}, with {size - pos} bytes after it; the first {len(chunks)} chunks are "
                    f"intact — replay them with --salvage"
                )
            break
        chunk = Chunk(kind, port[0], t, bytes(payload))
        if kind == MARK:
            try:
                markers.append(chunk.marker())
            except (UnicodeDecodeError, json.JSONDecodeError):
                raise RecordingError(f"{path}: marker chunk {len(chunks)} at byte {pos} is not valid JSON") from None
        chunks.append(chunk)
        pos = end
    return Recording(path, settings, chunks, size, pos if problem else size, problem, markers)


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
class Replay:
    """What replaying a recording gave: the frames, the decoding settings, events and counters."""

    frames: Frames
    setups: list[dict]
    events: list[dict]
    sessions: int
    resyncs: int
    dropped_records: int
    rejected_records: int


def replay(recording: Recording, on_frames=None, realtime: bool = False, speed: float = 1.0,
           batch_seconds: float = 0.05, on_progress=None) -> Replay:
    """Decode a recording through the same assembler as the live read (same bytes, same order, same
    arrival times), so the frames are identical to the ones the live reader delivered.

    `on_frames(frames)` is called with `Frames` in batches; with `realtime` the batches
    are paced by the recorded arrival times (divided by `speed`). `on_progress(chunks done)` is called
    every PROGRESS_CHUNKS chunks and at the end (for a progress bar).
    """
    parts, setups, events = [], [], []
    asm = None
    m = 0
    totals = dict(resyncs=0, dropped=0, rejected=0)
    wall0 = time.monotonic()
    rec0 = recording.chunks[0].time if recording.chunks else 0.0
    last_emit = rec0

    def collect(now: float, force: bool = False) -> None:
        nonlocal last_emit
        if asm is None or (not force and now - last_emit < batch_seconds):
            return
        last_emit = now
        out = asm.take()
        if len(out):
            parts.append(out)
            if on_frames is not None:
                if realtime:
                    delay = (now - rec0) / speed - (time.monotonic() - wall0)
                    if delay > 0:
                        time.sleep(delay)
                on_frames(out)

    def retire() -> None:
        nonlocal asm
        if asm is None:
            return
        asm.flush()
        collect(last_emit, force=True)
        totals["resyncs"] += asm.resyncs
        totals["dropped"] += asm.dropped_records
        totals["rejected"] += asm.rejected_records
        asm = None

    for k, chunk in enumerate(recording.chunks):
        if on_progress is not None and k % PROGRESS_CHUNKS == 0 and k:
            on_progress(k)
        if chunk.kind == MARK:
            info = chunk.marker()
            if "stream" in info:
                retire()
                setup = FlockSetup.from_dict(info["stream"])
                setups.append(info["stream"])
                m = setup.birds
                asm = FrameAssembler(setup, **info.get("assembler", {}))
                last_emit = chunk.time
            elif info.get("flush"):
                collect(chunk.time, force=True)
                retire()
            elif "event" in info:
                events.append(info)
        elif chunk.kind == READ and asm is not None:
            asm.feed(chunk.port, chunk.time, chunk.payload)
            collect(chunk.time)
    retire()
    if on_progress is not None:
        on_progress(len(recording.chunks))
    frames = Frames.concat(parts, m)
    return Replay(frames, setups, events, len(setups), totals["resyncs"], totals["dropped"], totals["rejected"])
