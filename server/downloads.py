"""Session downloads built from the frame log a chunk at a time, so memory stays bounded by the chunk
(a few MB) whatever the session's length: the .npz take here; the BVH motion, the glTF rig and the skeleton
file are flockcal.exports' own writers reading a `FrameFile` (a `flockcal.takes.ChunkedTake`).

Each reads the frames the log held when the download began (a live session keeps growing). The
outputs equal what flockcal.takes / flockcal.exports make of the whole take loaded at once.
"""

from __future__ import annotations

import asyncio
import logging
import threading
import zipfile
from pathlib import Path
from typing import Iterator

import numpy as np
from starlette.responses import FileResponse, StreamingResponse

from flockcal.frames import Frames
from flockcal.server.wsgate import abort

from flockcal.server.errors import Unavailable
from flockcal.server.framelog import FrameLogReader, record_dtype, sanitize, time_span  # noqa: F401 (record_dtype: chunk sizes)

log = logging.getLogger(__name__)

CHUNK_BYTES = 1024 * 1024  # frames read per step; per download the service holds a few of these
OUT_BYTES = 256 * 1024  # bytes handed to the connection at a time


class FrameFile:
    """A session's frame log opened for reading in chunks: names, rate, n frames (fixed at open). A
    `flockcal.takes.ChunkedTake`: the exports read it as they read a Take."""

    def __init__(self, path: str | Path):
        # Held open until `close()`: a download reads what it began with, whatever happens to the name
        # (retention and DELETE wait for it, server/holds.py; this is the last line of defence).
        self.log = FrameLogReader(path)  # FrameLogError (a ValueError) when cut or damaged
        try:
            self._open()
        except BaseException:
            self.log.close()
            raise

    def _open(self) -> None:
        self.path = self.log.path
        self.names: list[str] = list(self.log.names)
        self.m = self.log.m
        self.dtype = self.log.dtype
        self.n = self.log.n
        self.chunk = max(1, CHUNK_BYTES // self.dtype.itemsize)
        # Damaged records become frames with no valid sensor (server/framelog.py: sanitize), chunk by chunk
        # exactly as read_frames does for the whole log.
        self.span = time_span(self.log.frames(0, min(self.n, 100)).times,
                              self.log.frames(max(self.n - 100, 0), min(self.n, 100)).times)
        self.t0 = float(sanitize(self.log.frames(0, 1), self.span, -np.inf)[0].times[0]) if self.n else 0.0
        rate = self.log.rate_hz
        if not rate:  # as SessionManager.take: the mean rate of the arrivals
            last = float(sanitize(self.log.frames(self.n - 1, 1), self.span, self.t0)[0].times[0]) if self.n > 1 else self.t0
            span = last - self.t0
            rate = (self.n - 1) / span if span > 0 else 1.0
        self.rate_hz = float(rate)

    @property
    def n_frames(self) -> int:
        return self.n

    @property
    def play_frames(self) -> int:
        """Frames per step when played back: a quarter of a read chunk, as reconstruction and Euler angles
        hold ~10 arrays of its size."""
        return max(1, self.chunk // 4)

    def close(self) -> None:
        self.log.close()

    def chunks(self, size: int | None = None) -> Iterator[Frames]:
        """`Frames` (times from the first frame) per chunk of `size` frames (default CHUNK_BYTES' worth), as a
        Take holds them: invalid sensor-frames zeroed (flockcal.takes.make_take)."""
        last = -np.inf
        for raw in self.log.chunks(size or self.chunk):
            frames, last = sanitize(raw, self.span, last)
            yield Frames(frames.times - self.t0, frames.rotations, frames.positions, frames.valid)


DOWNLOAD_STALL_S = 30.0  # a download whose client takes no data for this long is cut off, its slot freed
SLOT_RETRY_AFTER_S = 10  # what a client refused a slot is told to wait


class DownloadSlots:
    """At most `limit` downloads built at once (each holds a few chunks and a thread while it runs):
    one more gets 503 (with Retry-After) and the number running, instead of memory and CPU growing with the
    clients. A client that stops reading gives its slot up after `stall_s` (`SlottedResponse`)."""

    def __init__(self, limit: int = 8, stall_s: float = DOWNLOAD_STALL_S):
        self.limit = limit
        self.stall_s = float(stall_s)
        self.running = 0
        self.stalled = 0  # downloads cut off because their client took no data for stall_s
        self._lock = threading.Lock()

    def acquire(self) -> None:
        with self._lock:
            if self.running >= self.limit:
                raise Unavailable(f"{self.running} downloads are being built already (the service builds at most "
                                  f"{self.limit} at once, and frees the slot of a client that reads nothing for "
                                  f"{self.stall_s:g} s); try again when one has finished",
                                  retry_after=SLOT_RETRY_AFTER_S)
            self.running += 1

    def release(self) -> None:
        with self._lock:
            self.running -= 1

    def status(self) -> dict:
        """For /api/status: the slots (`limit`), those held now (`running`), the stall time and how many
        downloads it has cut off (`stalled`)."""
        with self._lock:
            return {"limit": self.limit, "running": self.running, "stall_s": self.stall_s, "stalled": self.stalled}

    def guard(self, stream: Iterator[bytes]) -> "Slotted":
        return Slotted(stream, self.release)


class Slotted:
    """An iterator over `stream` that calls `release` once: at its end, on an error, or when it is
    dropped unfinished (a client gone before or during the response). A generator would not: one
    never started runs no `finally`."""

    def __init__(self, stream: Iterator[bytes], release):
        self._stream = stream
        self._release = release

    def __iter__(self):
        return self

    def __next__(self) -> bytes:
        try:
            return next(self._stream)
        except BaseException:
            self.close()
            raise

    def close(self) -> None:
        release, self._release = self._release, None
        if release is not None:
            release()
            close = getattr(self._stream, "close", None)
            if close is not None:
                close()

    def __del__(self):
        self.close()


class StallClock:
    """For a Starlette response: each piece of the body must be taken by the client within the download slots'
    `stall_s`, or the connection is reset (`on_stall` first frees what the download holds) and the slots count
    it stalled. A client that requested a download and stopped reading held it for good."""

    slots: DownloadSlots

    def on_stall(self) -> None:
        pass

    async def __call__(self, scope, receive, send) -> None:
        stall_s = self.slots.stall_s

        async def timed(message) -> None:
            if message["type"] != "http.response.body":
                await send(message)
                return
            async with asyncio.timeout(stall_s):
                await send(message)

        try:
            await super().__call__(scope, receive, timed)
        except TimeoutError:
            self.slots.stalled += 1
            log.warning("a download's client took no data for %g s: connection reset", stall_s)
            self.on_stall()
            abort(scope)


class SlottedResponse(StallClock, StreamingResponse):
    """A download in a slot, on the stall clock: a stalled client's slot is freed (eight such held every slot)."""

    def __init__(self, content: Slotted, slots: DownloadSlots, **kw):
        super().__init__(content, **kw)
        self.slotted = content
        self.slots = slots

    def on_stall(self) -> None:
        self.slotted.close()  # frees the slot now (the stream is idle: the stalled send holds this task)


class StallClockFileResponse(StallClock, FileResponse):
    """A file sent as it is (a stopped session's raw recording), on the stall clock but in no slot (a file
    costs the service no build); Range requests as FileResponse answers them."""

    def __init__(self, path, slots: DownloadSlots, release=None, **kw):
        super().__init__(path, **kw)
        self.slots = slots
        self.release = release  # called once the response has been sent, or the client went away

    async def __call__(self, scope, receive, send) -> None:
        try:
            await super().__call__(scope, receive, send)
        finally:
            if self.release is not None:
                self.release()


# --- .npz take ------------------------------------------------------------------------------------------
class _Sink:
    """The zip file's output: bytes pile up here until the generator hands them on."""

    def __init__(self):
        self.parts: list[bytes] = []
        self.size = 0

    def write(self, data) -> int:
        self.parts.append(bytes(data))
        self.size += len(data)
        return len(data)

    def flush(self) -> None:
        pass

    def take(self) -> bytes:
        out = b"".join(self.parts)
        self.parts.clear()
        self.size = 0
        return out


def npz_stream(frames: FrameFile) -> Iterator[bytes]:
    """The design.md §5 take of `frames` as .npz bytes (np.load reads it), written entry by entry:
    each .npy entry is its header then the array's rows, chunk by chunk.

    Stored, not deflated: a 16-bird log shrank by 6 % at about 12 MB/s of one core (an hour would
    take a core for over a minute per download); np.load reads either."""
    from numpy.lib import format as npy

    sink = _Sink()
    n, m = frames.n, frames.m
    names = np.asarray(frames.names, dtype=str)
    entries = [
        ("rotations", np.dtype("<f8"), (n, m, 3, 3), lambda c: c.rotations),
        ("positions", np.dtype("<f8"), (n, m, 3), lambda c: c.positions),
        ("valid", np.dtype(bool), (n, m), lambda c: c.valid),
        ("times", np.dtype("<f8"), (n,), lambda c: c.times),
    ]
    # ZIP64 from the start: an hour of 16 birds is past 4 GB-unaware sizes only for the rotations, but
    # a size is unknown until the entry ends and the header must allow for it.
    with zipfile.ZipFile(sink, mode="w", compression=zipfile.ZIP_STORED, allowZip64=True) as zf:
        for name, value in (("names", names), ("rate_hz", np.float64(frames.rate_hz))):
            with zf.open(name + ".npy", "w") as entry:
                npy.write_array(entry, np.asanyarray(value), allow_pickle=False)
        for name, dtype, shape, part in entries:
            with zf.open(name + ".npy", "w", force_zip64=True) as entry:
                npy.write_array_header_1_0(entry, {"descr": npy.dtype_to_descr(dtype), "fortran_order": False,
                                                   "shape": shape})
                for chunk in frames.chunks():
                    entry.write(np.ascontiguousarray(part(chunk), dtype=dtype).tobytes())
                    if sink.size >= OUT_BYTES:
                        yield sink.take()
            if sink.size:
                yield sink.take()
    yield sink.take()


def primed(stream: Iterator[bytes]) -> Iterator[bytes]:
    """Run `stream` to its first piece now, so its errors become a 4xx before the response starts."""
    first = next(stream)

    def rest():
        yield first
        yield from stream

    return rest()
