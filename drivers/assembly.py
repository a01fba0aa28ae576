"""Chunks of bytes with arrival times → frames (times, rotations, positions, valid), deterministically.

The live reader and replay both feed this one class, so a recording replays to byte-identical frames.
Decisions depend only on the chunks (their bytes and arrival times), never on the clock while processing.
Each port's framing is port_stream's; the checks that need a bird's past are checks'.
"""

from __future__ import annotations

import numpy as np

from flockcal.drivers.checks import BirdChecks
from flockcal.drivers.link import FlockSetup
from flockcal.drivers.port_stream import HeldRecords, PortStream
from flockcal.drivers.records import FORMATS, decode_block_words
from flockcal.frames import Frames, TrackerWords


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
                 coalesce_seconds: float = 0.01, words: bool = False):
        self.setup = setup
        self.keep_words = words  # the frames carry the data words their poses came from (Frames.words)
        self.format = FORMATS[setup.record_format]
        self.m = setup.birds
        if setup.mode == "point":  # a poll's answer should come out before the next poll
            coalesce_bytes, coalesce_seconds = 0, 0.0
        self.ports = [PortStream(setup, i, coalesce_bytes, coalesce_seconds)
                      for i in range(1 if setup.group else len(setup.urls))]
        self.period = 1.0 / max(setup.rate_hz, 1e-3)
        self.index_of_address = np.full(256, -1, np.int64)
        self.index_of_address[np.asarray(setup.addresses)] = np.arange(self.m)
        self.max_address = max(setup.addresses)
        # Group-mode records of the cycle still open.
        self.none = self.ports[0].none
        self.open = self.none
        # Cycles closed but not yet decoded: (cycle_times, cycle, bird, records) per batch.
        self.pending: list[tuple[np.ndarray, np.ndarray, np.ndarray, HeldRecords]] = []
        self.pending_cycles = 0
        # Decoded cycles held back from a suspect record on: (cycle_times, R, p, valid, suspect, rec_time,
        # clipped, words), until its bird's next record shows whether it was line noise (checks.decide_suspects).
        self.held: tuple | None = None
        # One-port-per-bird queues of released records.
        self.port_cycle = [-1] * len(self.ports)  # cycle number of each port's last record
        self.port_time = [-np.inf] * len(self.ports)
        self.cycle_slots: dict[int, dict[int, tuple[HeldRecords, int]]] = {}  # cycle → port → (records, index)
        self.cycle_time: dict[int, float] = {}
        self.newest = -1
        self.emitted_upto = -1
        # Cycles a port may lag behind the others before its slot is given up (host delays).
        self.patience = max(3, int(np.ceil(0.25 / self.period)))
        self.last_frame_time = -np.inf
        self.phase: float | None = None  # arrival time of cycle 0, once anchored
        # Records per port to read the flock's phase from: each port's least-delayed record decides, and a
        # busy host can deliver a port's first 8 (0.2 s at 40 Hz) in late bursts, which put that port a
        # cycle off for the whole stream; half a second of records makes a prompt one near certain.
        self.anchor_records = max(8, int(np.ceil(0.5 / self.period)))
        self.startup = [self.none for _ in self.ports]
        self.now = -np.inf
        self.last_seen = np.full(self.m, -np.inf)  # arrival of the last record of any kind, per bird
        self.out: list[Frames] = []
        self.events: list[tuple[str, str, dict]] = []
        self.frames = 0
        self.dropped_records = 0
        self.rejected_records = 0
        # Per-bird memory for the motion check and the hemisphere tracker.
        self.checks = BirdChecks(setup, self._event,
                                 hemisphere_tracking=hemisphere_tracking, max_speed=max_speed,
                                 max_turn_rate=max_turn_rate, saturation_quiet=saturation_quiet)

    # -- counters ------------------------------------------------------------------------------
    @property
    def resyncs(self) -> int:
        return sum(p.decoder.resyncs for p in self.ports)

    @property
    def dropped_bytes(self) -> int:
        return sum(p.decoder.dropped_bytes for p in self.ports)

    @property
    def saturated_records(self) -> int:
        """Bird-frames whose position was clipped at full scale."""
        return self.checks.saturated_records

    def _event(self, event: tuple[str, str, dict]) -> None:
        self.events.append(event)  # take_events swaps the list, so the checks cannot hold on to it

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

    def _framed(self, port: int, released: HeldRecords) -> None:
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
        self._finish(final=True)

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
    def _take_records(self, port: int, rec: HeldRecords, final: bool) -> None:
        if len(rec) == 0:
            return
        if self.setup.group:
            self.open = HeldRecords.concat([self.open, rec])
            self._emit_group(self.open, close_last=False)
        else:
            self._assign(port, rec, final)
            self._emit_ports(final=final)

    def _emit_group(self, rec: HeldRecords, close_last: bool) -> None:
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
    def _assign(self, port: int, rec: HeldRecords, final: bool = False) -> None:
        """Give each record of `port` its cycle number by counting: the one after the port's last record.

        Counting is what survives a busy host, where arrival times of one cycle on different ports can
        differ by a whole period. Time only anchors the count: at the start (each port's phase is the
        smallest `arrival − count·period` over its first records, since host delays only ever add), and
        after lost bytes or a long silence (the cycle nearest the flock's phase).
        """
        P = self.period
        if self.phase is None:
            self.startup[port] = HeldRecords.concat([self.startup[port], rec])
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

    def _place(self, port: int, rec: HeldRecords, cycles: np.ndarray) -> None:
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
        by_source: dict[int, tuple[HeldRecords, list[int], list[int], list[int]]] = {}  # records, index, cycle, bird
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
        rec = HeldRecords.concat([r.select(np.asarray(index)) for r, index, _, _ in sources])
        cycle = np.concatenate([np.asarray(cyc, np.int64) for _, _, cyc, _ in sources])
        birds = np.concatenate([np.asarray(bird, np.int64) for _, _, _, bird in sources])
        times = np.maximum.accumulate(np.maximum(np.asarray(times), self.last_frame_time))
        self.last_frame_time = float(times[-1])
        self._emit(times, cycle, birds, rec)

    # -- common: fill frames, check suspects, track hemisphere ---------------------------------
    def _emit(self, cycle_times: np.ndarray, cycle: np.ndarray, bird: np.ndarray, rec: HeldRecords) -> None:
        """Queue closed cycles (cycle numbers 0..n-1 within this call) for the next decode."""
        self.pending.append((cycle_times, cycle, bird, rec))
        self.pending_cycles += len(cycle_times)
        if self.pending_cycles >= self.batch_cycles:
            self._finish()

    def _finish(self, final: bool = False) -> None:
        """Decode and check every queued cycle in one batch (`final`: the stream ended, decide what is held)."""
        if not self.pending:
            if final and self.held is not None:
                self._check_cycles(*self.held, final=True)
            return
        pending, self.pending, self.pending_cycles = self.pending, [], 0
        if len(pending) == 1:
            cycle_times, cycle, bird, rec = pending[0]
        else:
            sizes = np.cumsum([0] + [len(x[0]) for x in pending[:-1]])
            cycle_times = np.concatenate([x[0] for x in pending])
            cycle = np.concatenate([x[1] + s for x, s in zip(pending, sizes)])
            bird = np.concatenate([x[2] for x in pending])
            rec = HeldRecords.concat([x[3] for x in pending])
        self._decode_cycles(cycle_times, cycle, bird, rec, final)

    def _decode_cycles(self, cycle_times: np.ndarray, cycle: np.ndarray, bird: np.ndarray, rec: HeldRecords,
                       final: bool = False) -> None:
        n, m = len(cycle_times), self.m
        words, rotations, positions, rec_valid, rec_clipped = decode_block_words(
            self.format, rec.raw, scale_inches=self.setup.scale_inches)
        grid = np.arange(n * m)
        if len(bird) == n * m and np.array_equal(bird, grid % m) and np.array_equal(cycle, grid // m):
            # Every bird of every cycle, in order (the usual case): the records already are the frames.
            R = rotations.reshape(n, m, 3, 3)
            p = positions.reshape(n, m, 3)
            W = words.reshape(n, m, -1)
            valid = rec_valid.reshape(n, m)
            suspect = (rec.suspect & rec_valid).reshape(n, m)
            rec_time = rec.times.reshape(n, m)
            np.maximum(self.last_seen, rec_time.max(axis=0), out=self.last_seen)
            clipped = rec_clipped.reshape(n, m)
        else:
            R = np.zeros((n, m, 3, 3))
            p = np.zeros((n, m, 3))
            W = np.zeros((n, m, words.shape[1]), words.dtype)
            valid = np.zeros((n, m), bool)
            suspect = np.zeros((n, m), bool)
            ok = bird >= 0
            c, b = cycle[ok], bird[ok]
            R[c, b] = rotations[ok]
            p[c, b] = positions[ok]
            W[c, b] = words[ok]
            valid[c, b] = rec_valid[ok]
            suspect[c, b] = rec.suspect[ok] & rec_valid[ok]
            rec_time = np.zeros((n, m))
            rec_time[c, b] = rec.times[ok]
            np.maximum.at(self.last_seen, b, rec.times[ok])
            clipped = np.zeros((n, m), bool)
            clipped[c, b] = rec_clipped[ok]
        self._check_cycles(cycle_times.astype(float), R, p, valid, suspect, rec_time, clipped, W, final)

    def _check_cycles(self, cycle_times, R, p, valid, suspect, rec_time, clipped, W, final: bool = False) -> None:
        """Decide the suspect records (holding back cycles from the first that waits for its bird's next
        record), then finish and queue the cycles before it as frames."""
        if self.held is not None:
            parts = (self.held, (cycle_times, R, p, valid, suspect, rec_time, clipped, W))
            cycle_times, R, p, valid, suspect, rec_time, clipped, W = (np.concatenate(x) for x in zip(*parts))
            self.held = None
        n = len(cycle_times)
        if suspect.any():
            n, rejected = self.checks.decide_suspects(cycle_times, R, p, valid, suspect, rec_time, final)
            self.rejected_records += rejected
            if n < len(cycle_times):
                self.held = tuple(x[n:] for x in (cycle_times, R, p, valid, suspect, rec_time, clipped, W))
                cycle_times, R, p, valid, rec_time, clipped, W = (x[:n] for x in (cycle_times, R, p, valid, rec_time,
                                                                                   clipped, W))
        if n == 0:
            return
        self.checks.apply(cycle_times, R, p, valid, rec_time, clipped if clipped.any() else None, W)
        R[~valid] = 0.0
        p[~valid] = 0.0
        self.frames += n
        self.dropped_records += int(np.count_nonzero(~valid))
        words = TrackerWords(W, self.format.command, self.setup.scale_inches) if self.keep_words else None
        self.out.append(Frames(cycle_times, R, p, valid, words))
