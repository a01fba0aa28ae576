"""Chunks of bytes with arrival times → frames (times, rotations, positions, valid), deterministically.

The live reader and replay both feed this one class, so a recording replays to byte-identical frames.
Decisions depend only on the chunks (their bytes and arrival times), never on the clock while processing.
"""

from __future__ import annotations


import numpy as np

from flockcal.drivers import codec
from flockcal.frames import Frames
from flockcal.drivers.link import FlockSetup


class _Held:
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
    def empty(length: int) -> "_Held":
        return _Held(np.zeros(0), np.zeros(0, np.int64), np.zeros((0, length), np.uint8),
                     np.zeros(0, bool), np.zeros(0, bool))

    def __len__(self) -> int:
        return len(self.times)

    @staticmethod
    def concat(parts: list["_Held"]) -> "_Held":
        parts = [p for p in parts if len(p)] or parts[:1]
        if len(parts) == 1:
            return parts[0]
        return _Held(*(np.concatenate([getattr(p, k) for p in parts]) for k in _HELD_FIELDS))

    def append(self, other: "_Held") -> "_Held":
        return _Held.concat([self, other])

    def split(self, k: int) -> tuple["_Held", "_Held"]:
        return (_Held(*(getattr(self, f)[:k] for f in _HELD_FIELDS)),
                _Held(*(getattr(self, f)[k:] for f in _HELD_FIELDS)))

    def select(self, sel) -> "_Held":
        return _Held(*(getattr(self, f)[sel] for f in _HELD_FIELDS))


_HELD_FIELDS = ("times", "addresses", "raw", "suspect", "after_gap")


class _PortStream:
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
            self.decoder = codec.StreamDecoder({a: fmt for a in setup.addresses}, group=True,
                                               scale_inches=setup.scale_inches)
        else:
            self.decoder = codec.StreamDecoder(fmt, group=False, address=setup.addresses[index],
                                               scale_inches=setup.scale_inches)
        self.length = codec.record_length(fmt, group=setup.group)
        self.none = _Held.empty(self.length)
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

    def frame_queued(self) -> _Held:
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
            new = _Held(times, rec.addresses, rec.record_bytes(L), flags, flags.copy())
        else:
            ends = offsets + L
            prev_ends = np.concatenate([[first_prev], ends[:-1]])
            prev_gap = offsets != prev_ends
            next_gap = np.zeros(k, bool)
            next_gap[:-1] = offsets[1:] != ends[:-1]
            new = _Held(times, rec.addresses, rec.record_bytes(L), prev_gap | next_gap, prev_gap)
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
        out = _Held.concat([out, release])
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

    def _release_all(self, next_gap: bool) -> _Held:
        out = self.held
        if next_gap and len(out):
            out.suspect[-1] = True
        self.held = self.none
        self.held_end = -1
        return out

    def flush(self) -> _Held:
        """Release what is held (the line went quiet or is being reset) and forget partial records."""
        queued = self.frame_queued()
        out = _Held.concat([queued, self._release_all(next_gap=False)])
        self.decoder.reset()
        self.prev_end = None
        return out


class FrameAssembler:
    """Feeds chunks to per-port decoders and groups the records into frames of one measurement cycle.

    Group mode: a cycle is a run of strictly increasing bird addresses on the one port. One port per
    bird: records are grouped by arrival time (nearest to the cycle's median arrival, within half a
    period). A bird whose record is missing, damaged, saturated, clipped at full scale or fails the
    motion check is invalid.

    Reads are framed and grouped into cycles as they come; the poses of finished cycles are decoded
    and checked in one batch when frames are taken (or every `batch_cycles` cycles). That work is the
    same whatever the batches, so frames depend only on the chunks fed, not on when `take` is called.
    """

    batch_cycles = 1024  # decode at least this often even if nobody takes frames

    def __init__(self, setup: FlockSetup, *, hemisphere_tracking: bool = True, max_speed: float = 20.0,
                 max_turn_rate: float = 60.0, saturation_quiet: float = 1.0, coalesce_bytes: int = 512,
                 coalesce_seconds: float = 0.01):
        self.setup = setup
        self.format = codec.FORMATS[setup.record_format]
        self.saturation_quiet = saturation_quiet
        self.m = setup.birds
        if setup.mode == "point":  # a poll's answer should come out before the next poll
            coalesce_bytes, coalesce_seconds = 0, 0.0
        self.ports = [_PortStream(setup, i, coalesce_bytes, coalesce_seconds)
                      for i in range(1 if setup.group else len(setup.urls))]
        self.period = 1.0 / max(setup.rate_hz, 1e-3)
        self.hemisphere_tracking = hemisphere_tracking
        self.max_speed = max_speed
        self.max_turn_rate = max_turn_rate
        self.index_of_address = np.full(256, -1, np.int64)
        self.index_of_address[np.asarray(setup.addresses)] = np.arange(self.m)
        self.max_address = max(setup.addresses)
        self.hemisphere = codec.hemisphere_vector(setup.hemisphere)
        # Group-mode records of the cycle still open.
        self.none = self.ports[0].none
        self.open = self.none
        # Cycles closed but not yet decoded: (cycle_times, cycle, bird, records) per batch.
        self.pending: list[tuple[np.ndarray, np.ndarray, np.ndarray, _Held]] = []
        self.pending_cycles = 0
        # One-port-per-bird queues of released records.
        self.port_cycle = [-1] * len(self.ports)  # cycle number of each port's last record
        self.port_time = [-np.inf] * len(self.ports)
        self.cycle_slots: dict[int, dict[int, tuple[_Held, int]]] = {}  # cycle → port → (records, index)
        self.cycle_time: dict[int, float] = {}
        self.newest = -1
        self.emitted_upto = -1
        # Cycles a port may lag behind the others before its slot is given up (host delays).
        self.patience = max(3, int(np.ceil(0.25 / self.period)))
        self.last_frame_time = -np.inf
        self.phase: float | None = None  # arrival time of cycle 0, once anchored
        self.anchor_records = 8
        self.startup = [self.none for _ in self.ports]
        self.now = -np.inf
        # Per-bird memory for the motion check and the hemisphere tracker.
        self.last_time = np.full(self.m, -np.inf)
        self.last_seen = np.full(self.m, -np.inf)  # arrival of the last record of any kind, per bird
        self.last_pos = np.full((self.m, 3), np.nan)
        self.last_rot = np.full((self.m, 3, 3), np.nan)
        self.flipped = np.zeros(self.m, bool)
        self.out: list[Frames] = []
        self.events: list[tuple[str, str, dict]] = []
        self.frames = 0
        self.dropped_records = 0
        self.rejected_records = 0
        self.saturated_records = 0  # bird-frames whose position was clipped at full scale
        self.last_saturated = -np.inf  # time of the last frame with a clipped position

    # -- counters ------------------------------------------------------------------------------
    @property
    def resyncs(self) -> int:
        return sum(p.decoder.resyncs for p in self.ports)

    @property
    def dropped_bytes(self) -> int:
        return sum(p.decoder.dropped_bytes for p in self.ports)

    # -- input ---------------------------------------------------------------------------------
    def feed(self, port: int, t: float, data: bytes) -> None:
        """Bytes that arrived on `port` at monotonic time `t`."""
        if port >= len(self.ports):
            return
        self.now = max(self.now, t)
        ps = self.ports[port]
        if not ps.put(data, t):
            return
        self._framed(port, ps.frame_queued())

    def _framed(self, port: int, released: _Held) -> None:
        ps = self.ports[port]
        if ps.decoder.resyncs != ps.resyncs_seen:
            lost = ps.decoder.dropped_bytes - ps.dropped_seen
            self.events.append(("resync", f"port {port}: {lost} byte(s) lost or garbled; resynchronised on the "
                                          f"phasing bit", {"port": port, "bytes": int(lost)}))
            ps.resyncs_seen, ps.dropped_seen = ps.decoder.resyncs, ps.decoder.dropped_bytes
        self._take_records(port, released, final=False)

    def flush(self) -> None:
        """The stream ended or broke: emit everything pending (its missing birds invalid) and start afresh."""
        for i, ps in enumerate(self.ports):
            if ps.queue:
                self._framed(i, ps.frame_queued())
        for i, ps in enumerate(self.ports):
            self._take_records(i, ps.flush(), final=False)
        if not self.setup.group and self.phase is None:
            self._assign(0, self.none, final=True)
        if self.setup.group:
            self._emit_group(self.open, close_last=True)
            self.open = self.none
        else:
            self._emit_ports(final=True)
        self._finish()

    def take(self) -> Frames:
        """Frames assembled since the last call."""
        self._finish()
        out, self.out = Frames.concat(self.out, self.m), []
        return out

    @property
    def ready(self) -> bool:
        """Whether `take` or `take_events` has anything to hand out (closed cycles or news)."""
        return bool(self.pending or self.out or self.events)

    def take_events(self) -> list[tuple[str, str, dict]]:
        self._finish()
        out, self.events = self.events, []
        return out

    # -- group mode ----------------------------------------------------------------------------
    def _take_records(self, port: int, rec: _Held, final: bool) -> None:
        if len(rec) == 0:
            return
        if self.setup.group:
            self.open = _Held.concat([self.open, rec])
            self._emit_group(self.open, close_last=False)
        else:
            self._assign(port, rec, final)
            self._emit_ports(final=final)

    def _emit_group(self, rec: _Held, close_last: bool) -> None:
        if len(rec) == 0:
            return
        cycle, keep = self._group_cycles(rec.addresses, rec.suspect)
        if not keep.all():
            self.rejected_records += int(np.count_nonzero(~keep))
            rec = rec.select(keep)
            cycle = cycle[keep]
            if len(rec) == 0:
                self.open = rec
                return
        a = rec.addresses
        new_cycle = np.concatenate([[True], cycle[1:] != cycle[:-1]])
        # Only a trusted record closes a cycle: suspects after the last trusted one (say, garbage that
        # framed as bird 1) stay open until trusted records show which cycle they belong to. The last
        # cycle stays open unless it already holds the highest address (nothing can follow).
        last = len(rec) - 1
        if not close_last and rec.suspect[-1]:
            trusted = np.flatnonzero(~rec.suspect)
            if len(trusted) and last - trusted[-1] <= 2 * self.m:  # (a long run of suspects: decide anyway)
                last = int(trusted[-1])
            elif not len(trusted) and len(rec) <= 2 * self.m:
                return
        n = int(cycle[last]) + 1
        done = n if (close_last or a[last] == self.max_address) else n - 1
        if done == 0:
            return
        k = int(np.searchsorted(cycle, done))
        closed, self.open = rec.split(k)
        cyc = cycle[:k]
        first = np.flatnonzero(new_cycle[:k])
        self._emit(closed.times[first], cyc, self.index_of_address[closed.addresses], closed)

    @staticmethod
    def _group_cycles(a: np.ndarray, suspect: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Cycle number of each group-mode record (a cycle is a run of increasing addresses).

        Only trusted records may end a cycle: a garbled record's address byte can be any bird's. A
        suspect record joins the cycle around it if its address fits between its trusted neighbours,
        and is dropped otherwise.
        """
        k = len(a)
        trusted = ~suspect
        idx = np.flatnonzero(trusted)
        cycle = np.zeros(k, np.int64)
        keep = np.ones(k, bool)
        if len(idx):
            at = a[idx]
            ct = np.cumsum(np.concatenate([[True], at[1:] <= at[:-1]])) - 1
            cycle[idx] = ct
        if suspect.any():
            s = np.flatnonzero(suspect)
            pos = np.searchsorted(idx, s)  # trusted neighbours: idx[pos-1] before, idx[pos] after
            has_prev, has_next = pos > 0, pos < len(idx)
            a_prev = np.where(has_prev, a[idx[np.maximum(pos - 1, 0)]] if len(idx) else 0, 0)
            c_prev = np.where(has_prev, cycle[idx[np.maximum(pos - 1, 0)]] if len(idx) else 0, 0)
            a_next = np.where(has_next, a[idx[np.minimum(pos, len(idx) - 1)]] if len(idx) else 256, 256)
            c_next = np.where(has_next, cycle[idx[np.minimum(pos, len(idx) - 1)]] if len(idx) else 0, c_prev + 1)
            same = has_next & (c_next == c_prev)
            fits_prev = (a[s] > a_prev) & (~same | (a[s] < a_next))
            fits_next = ~same & (a[s] < a_next)
            cycle[s] = np.where(fits_prev, c_prev, c_next)
            keep[s] = fits_prev | fits_next
            # Two suspects claiming one slot, or out of order among themselves: keep the first.
            order = np.lexsort((np.arange(k), a, cycle))
            dup = np.zeros(k, bool)
            dup[order[1:]] = (cycle[order[1:]] == cycle[order[:-1]]) & (a[order[1:]] == a[order[:-1]])
            keep &= ~(dup & suspect)
            if keep.any():
                kept = np.flatnonzero(keep)
                bad = np.zeros(k, bool)
                bad[kept[1:]] = cycle[kept[1:]] < cycle[kept[:-1]]
                keep &= ~bad
        return cycle, keep

    # -- one port per bird ---------------------------------------------------------------------
    def _assign(self, port: int, rec: _Held, final: bool = False) -> None:
        """Give each record of `port` its cycle number by counting: the one after the port's last record.

        Counting is what survives a busy host, where arrival times of one cycle on different ports can
        differ by a whole period. Time only anchors the count: at the start (each port's phase is the
        smallest `arrival − count·period` over its first records, since host delays only ever add), and
        after lost bytes or a long silence (the cycle nearest the flock's phase).
        """
        P = self.period
        if self.phase is None:
            self.startup[port] = _Held.concat([self.startup[port], rec])
            counts = [len(h) for h in self.startup]
            if not (min(counts) >= self.anchor_records or max(counts) >= 3 * self.anchor_records or final):
                return
            if max(counts) == 0:
                return
            phases = np.array([np.min(h.times - np.arange(len(h)) * P) if len(h) else np.inf
                               for h in self.startup])
            self.phase = float(phases.min())
            for b, h in enumerate(self.startup):
                if len(h):
                    first = int(round((phases[b] - self.phase) / P))
                    self._place(b, h, first + np.arange(len(h)))
            self.startup = [self.none for _ in self.ports]
            return
        cycles = np.empty(len(rec), np.int64)
        last, last_t = self.port_cycle[port], self.port_time[port]
        for k in range(len(rec)):  # per record, but one port per bird is never the bulk path
            t = float(rec.times[k])
            # A host delay of many periods is normal on a busy machine; a longer silence means lost cycles.
            if last >= 0 and not rec.after_gap[k] and t - last_t <= max(10 * P, 0.25):
                c = last + 1
            else:
                c = max(int(round((t - self.phase) / P)), last + 1)
            cycles[k] = c
            last, last_t = c, t
        self._place(port, rec, cycles)

    def _place(self, port: int, rec: _Held, cycles: np.ndarray) -> None:
        times = rec.times.tolist()
        for k, c in enumerate(cycles.tolist()):
            if c <= self.emitted_upto:
                self.rejected_records += 1  # its cycle is already out
                continue
            slot = self.cycle_slots.setdefault(c, {})
            if port in slot:
                self.rejected_records += 1  # two records claim one cycle: keep the later one
            slot[port] = (rec, k)  # gathered per source batch when the cycle is emitted
            t = times[k]
            self.cycle_time[c] = min(self.cycle_time.get(c, t), t)
            self.newest = max(self.newest, c)
        if len(cycles):
            self.port_cycle[port] = int(cycles[-1])
            self.port_time[port] = float(rec.times[-1])

    def _emit_ports(self, final: bool) -> None:
        """Emit cycles in order once every port has moved past them (or three cycles have followed)."""
        ready = []
        c = self.emitted_upto + 1
        while c <= self.newest:
            if c not in self.cycle_slots:
                c += 1
                continue
            done = (len(self.cycle_slots[c]) == len(self.ports) or final
                    or all(pc >= c for pc in self.port_cycle) or self.newest - c >= self.patience)
            if not done:
                break
            ready.append(c)
            c += 1
        if not ready:
            return
        self.emitted_upto = ready[-1]
        times = []
        by_source: dict[int, tuple[_Held, list[int], list[int], list[int]]] = {}  # records, index, cycle, bird
        for i, c in enumerate(ready):
            slot = self.cycle_slots.pop(c)
            times.append(self.cycle_time.pop(c))
            for b, (r, k) in slot.items():
                _, index, cyc, bird = by_source.setdefault(id(r), (r, [], [], []))
                index.append(k)
                cyc.append(i)
                bird.append(b)
        for c in [c for c in self.cycle_slots if c <= self.emitted_upto]:  # late records of emitted cycles
            self.rejected_records += len(self.cycle_slots.pop(c))
            self.cycle_time.pop(c, None)
        sources = list(by_source.values())
        rec = _Held.concat([r.select(np.asarray(index)) for r, index, _, _ in sources])
        cycle = np.concatenate([np.asarray(cyc, np.int64) for _, _, cyc, _ in sources])
        birds = np.concatenate([np.asarray(bird, np.int64) for _, _, _, bird in sources])
        times = np.maximum.accumulate(np.maximum(np.asarray(times), self.last_frame_time))
        self.last_frame_time = float(times[-1])
        self._emit(times, cycle, birds, rec)

    # -- common: fill frames, check suspects, track hemisphere ---------------------------------
    def _emit(self, cycle_times: np.ndarray, cycle: np.ndarray, bird: np.ndarray, rec: _Held) -> None:
        """Queue closed cycles (cycle numbers 0..n-1 within this call) for the next decode."""
        self.pending.append((cycle_times, cycle, bird, rec))
        self.pending_cycles += len(cycle_times)
        if self.pending_cycles >= self.batch_cycles:
            self._finish()

    def _finish(self) -> None:
        """Decode and check every queued cycle in one batch."""
        if not self.pending:
            return
        pending, self.pending, self.pending_cycles = self.pending, [], 0
        if len(pending) == 1:
            cycle_times, cycle, bird, rec = pending[0]
        else:
            sizes = np.cumsum([0] + [len(x[0]) for x in pending[:-1]])
            cycle_times = np.concatenate([x[0] for x in pending])
            cycle = np.concatenate([x[1] + s for x, s in zip(pending, sizes)])
            bird = np.concatenate([x[2] for x in pending])
            rec = _Held.concat([x[3] for x in pending])
        self._decode_cycles(cycle_times, cycle, bird, rec)

    def _decode_cycles(self, cycle_times: np.ndarray, cycle: np.ndarray, bird: np.ndarray, rec: _Held) -> None:
        n, m = len(cycle_times), self.m
        rotations, positions, rec_valid, rec_clipped = codec.decode_block(
            self.format, rec.raw, scale_inches=self.setup.scale_inches)
        grid = np.arange(n * m)
        if len(bird) == n * m and np.array_equal(bird, grid % m) and np.array_equal(cycle, grid // m):
            # Every bird of every cycle, in order (the usual case): the records already are the frames.
            R = rotations.reshape(n, m, 3, 3)
            p = positions.reshape(n, m, 3)
            valid = rec_valid.reshape(n, m)
            suspect = (rec.suspect & rec_valid).reshape(n, m)
            rec_time = rec.times.reshape(n, m)
            np.maximum(self.last_seen, rec_time.max(axis=0), out=self.last_seen)
            clipped = rec_clipped.reshape(n, m)
        else:
            R = np.zeros((n, m, 3, 3))
            p = np.zeros((n, m, 3))
            valid = np.zeros((n, m), bool)
            suspect = np.zeros((n, m), bool)
            ok = bird >= 0
            c, b = cycle[ok], bird[ok]
            R[c, b] = rotations[ok]
            p[c, b] = positions[ok]
            valid[c, b] = rec_valid[ok]
            suspect[c, b] = rec.suspect[ok] & rec_valid[ok]
            rec_time = np.zeros((n, m))
            rec_time[c, b] = rec.times[ok]
            np.maximum.at(self.last_seen, b, rec.times[ok])
            clipped = np.zeros((n, m), bool)
            clipped[c, b] = rec_clipped[ok]
        if rec_clipped.any():
            self._report_saturation(cycle_times, clipped)
        if suspect.any():
            self._check_suspects(R, p, valid, suspect, rec_time)
        if self.hemisphere_tracking and self.setup.record_format in ("position", "position_angles",
                                                                     "position_matrix", "position_quaternion"):
            self._track_hemisphere(p, valid)
        self._remember(R, p, valid, rec_time)
        R[~valid] = 0.0
        p[~valid] = 0.0
        self.frames += n
        self.dropped_records += int(np.count_nonzero(~valid))
        self.out.append(Frames(cycle_times.astype(float), R, p, valid))

    def _report_saturation(self, cycle_times: np.ndarray, clipped: np.ndarray) -> None:
        """Count clipped positions; one event per burst (clipping after `saturation_quiet` s without)."""
        self.saturated_records += int(np.count_nonzero(clipped))
        rows = np.flatnonzero(clipped.any(axis=1))
        t = cycle_times[rows]
        before = np.concatenate([[self.last_saturated], t[:-1]])
        scale = self.setup.scale_inches
        if scale < 72:
            fix = "use the 72-inch scale (--scale 72) or move the transmitter closer to the performance area"
        else:
            fix = f"{scale:g} in is the largest scale: move the transmitter closer to the performance area"
        for row in rows[t - before > self.saturation_quiet]:
            birds = [int(b) for b in np.flatnonzero(clipped[row])]
            self.events.append(("position_saturated",
                                f"bird(s) {', '.join(map(str, birds))} beyond the {scale:g}-inch position full "
                                f"scale: clipped positions are marked invalid — {fix}",
                                {"birds": birds, "scale_inches": float(scale)}))
        self.last_saturated = max(self.last_saturated, float(t[-1]))

    def _check_suspects(self, R, p, valid, suspect, rec_time) -> None:
        """Keep a suspect record only if it continues the bird's motion (a garbled one jumps far away)."""
        for f, b in zip(*np.nonzero(suspect)):  # rare: only records next to lost bytes
            prev = np.flatnonzero(valid[:f, b])
            if len(prev):
                q, Q, tq = p[prev[-1], b], R[prev[-1], b], rec_time[prev[-1], b]
            else:
                q, Q, tq = self.last_pos[b], self.last_rot[b], self.last_time[b]
            dt = rec_time[f, b] - tq
            keep = False
            if np.isfinite(dt) and dt <= 0.5:
                dt = max(dt, 1.0 / max(self.setup.rate_hz, 1.0))
                keep = True
                if np.all(np.isfinite(p[f, b])) and np.all(np.isfinite(q)):
                    # Mirror-tolerant: a hemisphere crossing flips the reported position.
                    jump = min(np.linalg.norm(p[f, b] - q), np.linalg.norm(p[f, b] + q))
                    keep &= jump <= self.max_speed * dt + 0.03
                if np.all(np.isfinite(R[f, b])) and np.all(np.isfinite(Q)):
                    cos = (np.trace(Q.T @ R[f, b]) - 1.0) / 2.0
                    keep &= np.arccos(np.clip(cos, -1.0, 1.0)) <= self.max_turn_rate * dt + 0.2
            if not keep:
                valid[f, b] = False
                self.rejected_records += 1

    def _track_hemisphere(self, p: np.ndarray, valid: np.ndarray) -> None:
        """Undo hemisphere folding: the bird reports −p once a sensor crosses into the other hemisphere.

        Consecutive valid raw positions pointing to opposite sides (p·q < 0) can only be such a flip (a
        real move would have to pass through the transmitter). Positions are corrected in place.
        """
        n = len(p)
        if valid.all():  # the usual case: each bird's previous position is the row above
            prev = np.concatenate([self.last_raw_pos()[None], p[:-1]])
            raw_last = p[-1].copy()
        else:
            rows = np.arange(n)[:, None]
            idx = np.where(valid, rows, -1)
            last = np.maximum.accumulate(idx, axis=0)
            prev_idx = np.vstack([np.full((1, self.m), -1), last[:-1]])
            cols = np.arange(self.m)[None, :]
            prev = np.where((prev_idx >= 0)[..., None], p[np.maximum(prev_idx, 0), cols], self.last_raw_pos())
            raw_last = np.where((last[-1] >= 0)[:, None], p[np.maximum(last[-1], 0), np.arange(self.m)],
                                self.last_raw_pos())
        toggle = valid & (np.einsum("nmi,nmi->nm", p, prev) < 0)
        if toggle.any():
            for b in np.flatnonzero(toggle.any(axis=0)):
                self.events.append(("hemisphere_flip", f"bird {b} crossed the hemisphere boundary "
                                    f"{int(toggle[:, b].sum())} time(s); positions corrected",
                                    {"bird": int(b), "count": int(toggle[:, b].sum())}))
        self._raw_last = raw_last
        if not toggle.any():
            if self.flipped.any():
                p[:, self.flipped] *= -1.0
            return
        parity = (np.cumsum(toggle, axis=0) + self.flipped[None, :]) % 2 == 1
        self.flipped = parity[-1].copy()
        p[parity] *= -1.0

    def last_raw_pos(self) -> np.ndarray:
        return getattr(self, "_raw_last", np.full((self.m, 3), np.nan))

    def _remember(self, R, p, valid, rec_time) -> None:
        if valid[-1].all():
            self.last_pos[:] = p[-1]
            self.last_rot[:] = R[-1]
            self.last_time[:] = rec_time[-1]
            return
        seen = valid.any(axis=0)
        if not seen.any():
            return
        last = len(valid) - 1 - np.argmax(valid[::-1], axis=0)
        b = np.flatnonzero(seen)
        self.last_pos[b] = p[last[b], b]
        self.last_rot[b] = R[last[b], b]
        self.last_time[b] = rec_time[last[b], b]
