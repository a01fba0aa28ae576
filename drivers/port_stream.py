"""One port's records on their way to frames: framed as bytes arrive, the last one held back.

`PortStream` frames a port's chunks (coalescing tiny reads), marks records next to lost bytes as
suspect, and releases `HeldRecords` (still raw bytes: poses are decoded once per batch, in assembly).
"""

from __future__ import annotations

import numpy as np

from flockcal.drivers.link import FlockSetup
from flockcal.drivers.records import record_length
from flockcal.drivers.stream import StreamDecoder


class HeldRecords:
    """Records of one port framed but not yet released (we wait to see what follows the last one).

    Poses stay as raw record bytes until frames are handed out: decoding is done once per batch of
    many reads, not once per read.
    """

    __slots__ = ("times", "addresses", "raw", "suspect", "after_gap")

    def __init__(self, times, addresses, raw, suspect, after_gap):
        self.times = times  # (k,) arrival (or back-dated) time of each record
        self.addresses = addresses  # (k,) FBB address
        self.raw = raw  # (k, L) uint8 record bytes
        self.suspect = suspect  # (k,) bool: next to lost bytes, must continue the bird's motion
        self.after_gap = after_gap  # (k,) bool: lost bytes just before it

    @staticmethod
    def empty(length: int) -> "HeldRecords":
        return HeldRecords(np.zeros(0), np.zeros(0, np.int64), np.zeros((0, length), np.uint8),
                     np.zeros(0, bool), np.zeros(0, bool))

    def __len__(self) -> int:
        return len(self.times)

    @staticmethod
    def concat(parts: list["HeldRecords"]) -> "HeldRecords":
        parts = [p for p in parts if len(p)] or parts[:1]
        if len(parts) == 1:
            return parts[0]
        return HeldRecords(*(np.concatenate([getattr(p, k) for p in parts]) for k in _FIELDS))

    def append(self, other: "HeldRecords") -> "HeldRecords":
        return HeldRecords.concat([self, other])

    def split(self, k: int) -> tuple["HeldRecords", "HeldRecords"]:
        return (HeldRecords(*(getattr(self, f)[:k] for f in _FIELDS)),
                HeldRecords(*(getattr(self, f)[k:] for f in _FIELDS)))

    def select(self, sel) -> "HeldRecords":
        return HeldRecords(*(getattr(self, f)[sel] for f in _FIELDS))


_FIELDS = ("times", "addresses", "raw", "suspect", "after_gap")


class PortStream:
    """One port's decoder plus the check that tells a whole record from a damaged one.

    A record window can be clean (phasing bit first, none inside) and still be wrong: bytes inserted
    inside a record push its tail out of the window. Such a record is always followed (or preceded) by
    lost bytes, so every record next to lost bytes is marked suspect and must agree with the bird's
    motion before it is used. The last record of a chunk is held until the next bytes show what follows.

    Tiny reads are queued and framed together once `coalesce_bytes` have arrived or the queue spans
    `coalesce_seconds` of arrival time: the decision depends only on the chunks, so replay agrees.
    """

    def __init__(self, setup: FlockSetup, index: int, coalesce_bytes: int = 0, coalesce_seconds: float = 0.0):
        fmt = setup.record_format
        self.group = setup.group
        self.period = 1.0 / max(setup.rate_hz, 1e-3)
        self.last_time = -np.inf
        if setup.group:
            self.decoder = StreamDecoder({a: fmt for a in setup.addresses}, group=True,
                                               scale_inches=setup.scale_inches)
        else:
            self.decoder = StreamDecoder(fmt, group=False, address=setup.addresses[index],
                                               scale_inches=setup.scale_inches)
        self.length = record_length(fmt, group=setup.group)
        self.none = HeldRecords.empty(self.length)
        self.fed = 0  # stream bytes fed
        self.prev_end: int | None = None  # stream offset just after the last record released
        self.held = self.none
        self.held_end = -1
        self.resyncs_seen = 0
        self.dropped_seen = 0
        self.coalesce_bytes = coalesce_bytes
        self.coalesce_seconds = coalesce_seconds
        self.queue: list[bytes] = []
        self.queue_times: list[float] = []
        self.queued = 0

    def put(self, data: bytes, t: float) -> bool:
        """Queue a read; True when the queue should be framed now."""
        self.queue.append(bytes(data))
        self.queue_times.append(t)
        self.queued += len(data)
        return self.queued >= self.coalesce_bytes or t - self.queue_times[0] >= self.coalesce_seconds

    def frame_queued(self) -> HeldRecords:
        """Frame every queued read; the records it releases."""
        if not self.queue:
            return self.none
        chunks, times, n = self.queue, self.queue_times, self.queued
        self.queue, self.queue_times, self.queued = [], [], 0
        rec = self.decoder.frame_chunks(chunks, times)
        self.fed += n
        pending = self.decoder.pending_bytes
        tail_start = self.fed - pending
        k = len(rec)
        if k == 0:
            if len(self.held) and tail_start != self.held_end:
                return self._release_all(next_gap=True)  # bytes after the held record were lost
            if len(self.held) and pending:
                return self._release_all(next_gap=False)  # a new record starts right after it
            return self.none
        offsets = rec.offsets
        times = rec.times
        if not self.group:
            times = self._backdate(times)
        L = self.length
        first_prev = self.held_end if len(self.held) else (int(offsets[0]) if self.prev_end is None
                                                           else self.prev_end)
        last_end = int(offsets[-1]) + L
        if rec.contiguous and int(offsets[0]) == first_prev:
            # Whole records back to back, right after the previous one: nothing lost around them.
            flags = np.zeros(k, bool)
            new = HeldRecords(times, rec.addresses, rec.record_bytes(L), flags, flags.copy())
        else:
            ends = offsets + L
            prev_ends = np.concatenate([[first_prev], ends[:-1]])
            prev_gap = offsets != prev_ends
            next_gap = np.zeros(k, bool)
            next_gap[:-1] = offsets[1:] != ends[:-1]
            new = HeldRecords(times, rec.addresses, rec.record_bytes(L), prev_gap | next_gap, prev_gap)
            if len(self.held):
                self.held.suspect = self.held.suspect | prev_gap[:1]
        out = self.held
        # The last record: known good on the right if a new record starts right after it.
        if last_end != tail_start:
            new.suspect[-1] = True
            release, keep = new, self.none
        elif pending:
            release, keep = new, self.none
        else:
            release, keep = new.split(k - 1)
        out = HeldRecords.concat([out, release])
        self.held = keep
        self.held_end = last_end if len(keep) else -1
        self.prev_end = last_end
        return out

    def _backdate(self, times: np.ndarray) -> np.ndarray:
        """Records read in one chunk were made a period apart: date all but the last accordingly."""
        k = np.arange(len(times))
        last_of_run = np.searchsorted(times, times, side="right") - 1
        est = times - (last_of_run - k) * self.period
        est = np.maximum.accumulate(np.maximum(est, self.last_time))
        self.last_time = float(est[-1])
        return est

    def _release_all(self, next_gap: bool) -> HeldRecords:
        out = self.held
        if next_gap and len(out):
            out.suspect[-1] = True
        self.held = self.none
        self.held_end = -1
        return out

    def flush(self) -> HeldRecords:
        """Release what is held (the line went quiet or is being reset) and forget partial records."""
        queued = self.frame_queued()
        out = HeldRecords.concat([queued, self._release_all(next_gap=False)])
        self.decoder.reset()
        self.prev_end = None
        return out
