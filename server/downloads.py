"""Session downloads built from the frame log a chunk at a time, so memory stays bounded by the chunk
(a few MB) whatever the session's length: the .npz take, the BVH motion, the glTF rig and the skeleton file.

Each reads the frames the log held when the download began (a live session keeps growing). The
outputs equal what flockcal.takes / flockcal.exports make of the whole take loaded at once.
"""

from __future__ import annotations

import asyncio
import io
import logging
import os
import threading
import zipfile
from pathlib import Path
from typing import Iterator

import numpy as np
from starlette.responses import StreamingResponse

from flockcal.server.wsgate import abort

from flockcal.server.errors import Unavailable
from flockcal.server.framelog import parse_header, record_dtype, sanitize, time_span

log = logging.getLogger(__name__)

CHUNK_BYTES = 1024 * 1024  # frames read per step; per download the service holds a few of these
OUT_BYTES = 256 * 1024  # bytes handed to the connection at a time


class FrameFile:
    """A session's frame log opened for reading in chunks: names, rate, n frames (fixed at open)."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        with open(self.path, "rb") as fh:
            line = fh.readline()
            self.offset = fh.tell()
        header = parse_header(line, self.path.name)  # FrameLogError (a ValueError) when cut or damaged
        self.names: list[str] = list(header["names"])
        self.m = len(self.names)
        self.dtype = record_dtype(self.m)
        self.n = (os.path.getsize(self.path) - self.offset) // self.dtype.itemsize
        self.chunk = max(1, CHUNK_BYTES // self.dtype.itemsize)
        # Damaged records become frames with no valid sensor (server/framelog.py: sanitize), chunk by chunk
        # exactly as read_frames does for the whole log.
        self.span = time_span(self.records(0, min(self.n, 100))["time"],
                              self.records(max(self.n - 100, 0), min(self.n, 100))["time"])
        self.t0 = float(sanitize(self.records(0, 1), self.span, -np.inf)[0][0]) if self.n else 0.0
        rate = header.get("rate_hz")
        if not rate:  # as SessionManager.take: the mean rate of the arrivals
            span = float(sanitize(self.records(self.n - 1, 1), self.span, self.t0)[0][0]) - self.t0 if self.n > 1 else 0.0
            rate = (self.n - 1) / span if span > 0 else 1.0
        self.rate_hz = float(rate)

    def records(self, start: int, count: int) -> np.ndarray:
        with open(self.path, "rb") as fh:
            fh.seek(self.offset + start * self.dtype.itemsize)
            return np.fromfile(fh, dtype=self.dtype, count=count)

    def chunks(self, size: int | None = None) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
        """(times from the first frame, rotations, positions, valid) per chunk of `size` frames (default
        CHUNK_BYTES' worth), as a Take holds them: invalid sensor-frames zeroed (flockcal.takes.make_take)."""
        size = size or self.chunk
        last = -np.inf
        with open(self.path, "rb") as fh:
            fh.seek(self.offset)
            left = self.n
            while left > 0:
                rec = np.fromfile(fh, dtype=self.dtype, count=min(size, left))
                if not len(rec):
                    return
                left -= len(rec)
                times, R, t, valid, last = sanitize(rec, self.span, last)
                yield times - self.t0, R, t, valid


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


class SlottedResponse(StreamingResponse):
    """A download in a slot: each piece must be taken by the client within the slots' `stall_s`, or the
    connection is reset and the slot freed (a client that requested a take and stopped reading held its
    slot for good, and eight such held every slot)."""

    def __init__(self, content: Slotted, slots: DownloadSlots, **kw):
        super().__init__(content, **kw)
        self.slotted = content
        self.slots = slots
        self._scope = None

    async def __call__(self, scope, receive, send) -> None:
        self._scope = scope
        await super().__call__(scope, receive, send)

    async def stream_response(self, send) -> None:
        await send({"type": "http.response.start", "status": self.status_code, "headers": self.raw_headers})
        async for chunk in self.body_iterator:
            try:
                async with asyncio.timeout(self.slots.stall_s):
                    await send({"type": "http.response.body", "body": chunk, "more_body": True})
            except TimeoutError:
                self.slots.stalled += 1
                log.warning("a download's client took no data for %g s: connection reset, slot freed",
                            self.slots.stall_s)
                self.slotted.close()  # frees the slot now (the stream is idle: this task holds it)
                abort(self._scope or {})
                return
        await send({"type": "http.response.body", "body": b"", "more_body": False})


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
        ("rotations", np.dtype("<f8"), (n, m, 3, 3), lambda c: c[1]),
        ("positions", np.dtype("<f8"), (n, m, 3), lambda c: c[2]),
        ("valid", np.dtype(bool), (n, m), lambda c: c[3]),
        ("times", np.dtype("<f8"), (n,), lambda c: c[0]),
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


# --- rigidly attached sensors, BVH ------------------------------------------------------------------
def rigid_means(frames: FrameFile, art) -> dict[tuple[str, str], np.ndarray]:
    """{(sensor, parent): mean of R_pᵀ (t_j − t_p) over frames where both are valid} for every body of
    `art` that rides rigidly on its parent (Articulation.completed from the whole take, chunk by chunk)."""
    todo = np.flatnonzero(art.incomplete)
    if not len(todo):
        return {}
    index = [frames.names.index(art.names[i]) for i in range(art.n_bodies)]
    j = np.array([index[i] for i in todo])
    p = np.array([index[art.parent[i]] for i in todo])
    total, count = np.zeros((len(todo), 3)), np.zeros(len(todo))
    for _times, R, t, valid in frames.chunks():
        rel = np.einsum("nkba,nkb->nka", R[:, p], t[:, j] - t[:, p])
        ok = valid[:, j] & valid[:, p]
        total += np.where(ok[..., None], rel, 0.0).sum(axis=0)
        count += ok.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = total / count[:, None]
    return {(art.names[i], art.names[art.parent[i]]): mean[k] for k, i in enumerate(todo)}


class RigidPoints:
    """What Articulation.completed(acc=…) asks an accumulator for, answered from `rigid_means`."""

    def __init__(self, art, means: dict):
        self.names = art.names
        self.means = means

    def pair_point(self, x, j, p) -> np.ndarray:
        return np.array([self.means[(self.names[a], self.names[b])] for a, b in zip(np.atleast_1d(j), np.atleast_1d(p))])


def completed(art, frames: FrameFile):
    """`art` with its rigidly attached bodies placed from the whole log (as bvh_text does from a take)."""
    from flockcal.solver.reconstruct import ArticulationError

    if not art.incomplete.any():
        return art
    try:
        return art.completed(acc=RigidPoints(art, rigid_means(frames, art)))
    except KeyError:
        raise ArticulationError("a rigidly attached sensor is not in the recording") from None


def first_valid_pose(frames: FrameFile) -> tuple[np.ndarray, np.ndarray]:
    """(m, 3, 3), (m, 3): each sensor's first valid pose (what a Take holds before a sensor's first record)."""
    from flockcal.solver.reconstruct import ArticulationError

    R0 = np.full((frames.m, 3, 3), np.nan)
    t0 = np.full((frames.m, 3), np.nan)
    todo = np.ones(frames.m, dtype=bool)
    for _times, R, t, valid in frames.chunks():
        found = todo & valid.any(axis=0)
        if found.any():
            k = valid.argmax(axis=0)
            cols = np.flatnonzero(found)
            R0[cols], t0[cols] = R[k[cols], cols], t[k[cols], cols]
            todo &= ~found
        if not todo.any():
            break
    if todo.any():
        raise ArticulationError(f"sensor index(es) {np.flatnonzero(todo).tolist()} never gave a valid record; "
                                "nothing to play back")
    return R0, t0


def played_chunks(frames: FrameFile, art, carry_R: np.ndarray, carry_t: np.ndarray):
    """The log reconstructed through `art` (solver.reconstruct) a chunk at a time, as a whole Take would be.

    A Take holds each sensor's last valid pose through its dropouts, its first before it starts
    (`first_valid_pose`, passed in): carried from chunk to chunk as a leading frame every sensor is valid
    in. A quarter of a read chunk per step: reconstruction and Euler angles hold ~10 arrays of its size."""
    from flockcal.solver.reconstruct import held_poses, reconstruct

    for _times, R, t, valid in frames.chunks(max(1, frames.chunk // 4)):
        R = np.concatenate([carry_R[None], R])
        t = np.concatenate([carry_t[None], t])
        ok = np.concatenate([np.ones((1, frames.m), dtype=bool), valid])
        R, t = held_poses(R, t, ok)
        carry_R, carry_t = R[-1], t[-1]
        yield reconstruct(R[1:], t[1:], art)


def bvh_stream(calibration: dict, frames: FrameFile, units: str = "cm", up: str = "-z") -> Iterator[bytes]:
    """flockcal.exports.bvh.bvh_text(calibration, take, units=, up=) for the frame log, chunk by chunk.

    Errors in the calibration or the recording are raised by the first next(), before any byte."""
    from flockcal.exports.bvh import BvhError, UNITS_PER_METRE, bvh_world, hierarchy_text, motion_channels
    from flockcal.solver.reconstruct import articulation

    if units not in UNITS_PER_METRE:
        raise BvhError(f"units must be one of {', '.join(UNITS_PER_METRE)}, got {units!r}")
    scale = UNITS_PER_METRE[units]
    world = bvh_world(up)
    art = articulation(calibration).reordered(frames.names)
    art = completed(art, frames)
    carry_R, carry_t = first_valid_pose(frames)  # what a Take holds before each sensor's first record
    A = world @ carry_R  # rest_frames(rest="first"): the held rotations of frame 0
    yield (hierarchy_text(art, scale, A) + f"MOTION\nFrames: {frames.n}\nFrame Time: {1.0 / frames.rate_hz:.8f}\n"
           ).encode("ascii")
    for rec in played_chunks(frames, art, carry_R, carry_t):
        out = io.StringIO()
        np.savetxt(out, motion_channels(rec, world, scale, A), fmt="%.6f")
        yield out.getvalue().encode("ascii")


def gltf_stream(calibration: dict, frames: FrameFile, up: str = "-z", name: str = "take",
                rest: str = "first", animation: bool = True) -> Iterator[bytes]:
    """flockcal.exports.gltf.gltf_bytes(calibration, take, up=, rest=) for the frame log (rest "first" or "sensor"): the .glb's head first,
    then its buffer, whose animation blocks are filled chunk by chunk in a temporary file (glTF keeps
    each joint's keyframes in one block, so a chunk's rows land in every block). Errors in the
    calibration or the recording are raised by the first next(), before any byte. animation=False: the
    rig alone (193 kB for 16 bodies, no pass over the frames but the first valid pose and any rigid sensor's mean)."""
    import tempfile

    from flockcal.exports.bvh import bvh_world
    from flockcal.exports.gltf import animation_rows, build_rig, file_extras, glb_head, joint_notes, key_times, layout
    from flockcal.solver.reconstruct import articulation

    world = bvh_world(up)
    art = completed(articulation(calibration).reordered(frames.names), frames)
    carry_R, carry_t = first_valid_pose(frames)
    # rest_frames: "first" as bvh_stream; "sensor" keeps the sensor axes (the live pose's `rig` frame).
    A = np.broadcast_to(np.eye(3), carry_R.shape) if rest == "sensor" else world @ carry_R
    root = art.root
    rig = build_rig(art, A, world @ (carry_R[root] @ art.c[root] + carry_t[root]), joint_notes(calibration))
    if not animation:
        plan = layout(rig, None, name=name, extras=file_extras(up, rest, frames.rate_hz))
        yield glb_head(plan.doc, plan.size) + b"".join(plan.parts)
        return
    times = np.concatenate([chunk[0] for chunk in frames.chunks()])  # 8 bytes a frame: an hour is 4 MB
    plan = layout(rig, key_times(times, frames.rate_hz), name=name, extras=file_extras(up, rest, frames.rate_hz))
    del times
    yield glb_head(plan.doc, plan.size)
    with tempfile.TemporaryFile() as buf:
        for part in plan.parts:
            if isinstance(part, bytes):
                buf.write(part)
            else:
                buf.seek(part, os.SEEK_CUR)  # a reserved block: filled below
        buf.truncate(plan.size)
        k, last = 0, None
        for rec in played_chunks(frames, art, carry_R, carry_t):
            quats, root_rows = animation_rows(rec, world, A, rig, previous=last)
            last = quats[-1]
            for at, rows, width in [(plan.root_at, root_rows, 12)] + [
                    (plan.rotation_at[j], quats[:, j], 16) for j in range(quats.shape[1])]:
                buf.seek(at + k * width)
                buf.write(np.ascontiguousarray(rows).tobytes())
            k += len(quats)
        buf.seek(0)
        while piece := buf.read(OUT_BYTES):
            yield piece


def primed(stream: Iterator[bytes]) -> Iterator[bytes]:
    """Run `stream` to its first piece now, so its errors become a 4xx before the response starts."""
    first = next(stream)

    def rest():
        yield first
        yield from stream

    return rest()
