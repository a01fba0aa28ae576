"""Framing a byte stream of records: where each record starts, when it arrived, and its decoding.

`StreamDecoder` accepts a record only when it is whole and clean (protocol.md §4), resyncs on garbage
or lost bytes at the cost of the broken record alone, and stamps every record with its arrival time.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flockcal.drivers.records import RecordFormat, as_format, decode_block, record_length
from flockcal.drivers.words import PHASE_BIT, as_u8


@dataclass
class DecodedRecords:
    """Records found in a stream, in order: arrays over k records."""

    addresses: np.ndarray  # (k,) int
    rotations: np.ndarray  # (k, 3, 3) body → transmitter
    positions: np.ndarray  # (k, 3) metres
    valid: np.ndarray  # (k,) bool — False for the all-zero record and for a position at full scale
    offsets: np.ndarray  # (k,) int64, stream offset of each record's first byte
    times: np.ndarray  # (k,) float, arrival time of each record's first byte (NaN if unknown)
    buttons: np.ndarray | None = None  # (k,) uint8 when button mode is on
    clipped: np.ndarray | None = None  # (k,) bool, True where a position word sits at full scale

    def __len__(self) -> int:
        return len(self.addresses)

    @staticmethod
    def empty(button: bool = False) -> "DecodedRecords":
        return DecodedRecords(np.zeros(0, np.int64), np.zeros((0, 3, 3)), np.zeros((0, 3)),
                              np.zeros(0, bool), np.zeros(0, np.int64), np.zeros(0),
                              np.zeros(0, np.uint8) if button else None, np.zeros(0, bool))


@dataclass
class FramedRecords:
    """Records found in a stream but not yet decoded: where their bytes are, and when they arrived.

    Framing is cheap integer work done on every read; decoding poses can wait and be done for many
    reads at once (`StreamDecoder.decode`, or `record_bytes` + `decode_block`).
    """

    buffer: np.ndarray  # uint8 bytes the starts index into
    starts: np.ndarray  # (k,) index of each record's first byte in `buffer`
    lengths: np.ndarray | int  # (k,) record lengths, or one int for all
    addresses: np.ndarray  # (k,) int, the group address byte (or the stream's one address)
    offsets: np.ndarray  # (k,) int64 stream offsets
    times: np.ndarray  # (k,) arrival time of each record's first byte
    contiguous: bool = False  # records of one length back to back from buffer[0]

    def __len__(self) -> int:
        return len(self.starts)

    def record_bytes(self, length: int) -> np.ndarray:
        """(k, length) uint8: the bytes of every record (all of this length)."""
        k = len(self.starts)
        if self.contiguous:
            return self.buffer[:k * length].reshape(k, length)
        return self.buffer[self.starts[:, None] + np.arange(length)]




class _Arrivals:
    """Arrival time of any byte of a framing buffer: the old tail, then one or more reads.

    Only the buffer's first byte can come from the tail (the tail's one phasing byte), so the tail
    needs one time; reads are located by their cumulative ends.
    """

    __slots__ = ("n_tail", "tail_time", "last", "ends", "times")

    def __init__(self, n_tail: int, tail_time: float, last: float, ends=None, times=None):
        self.n_tail, self.tail_time, self.last, self.ends, self.times = n_tail, tail_time, last, ends, times

    def at(self, index: np.ndarray) -> np.ndarray:
        if self.ends is None:
            out = np.full(len(index), self.last)
        else:
            out = self.times[np.minimum(np.searchsorted(self.ends, index - self.n_tail, side="right"),
                                        len(self.times) - 1)]
        if self.n_tail and len(index) and index[0] == 0:
            out[0] = self.tail_time
        return out

    def at_index(self, i: int) -> float:
        if self.n_tail and i == 0:
            return self.tail_time
        if self.ends is None:
            return self.last
        return float(self.times[min(int(np.searchsorted(self.ends, i - self.n_tail, side="right")),
                                    len(self.times) - 1)])


class StreamDecoder:
    """Incremental framing of a record stream, vectorised over each chunk fed.

    A record starts at a byte with the phasing bit; it is accepted only when complete, every
    other byte has bit 7 clear and (group mode) its address byte is a configured bird whose
    format gives that length. Anything else is dropped; a broken record costs only itself.
    """

    def __init__(self, formats: RecordFormat | str | dict[int, RecordFormat | str], *,
                 group: bool, n_birds: int | None = None, scale_inches: float = 36.0,
                 button: bool = False, address: int = 0,
                 quaternion_convention: str = "fob") -> None:
        self.group = group
        self.button = button
        self.scale_inches = scale_inches
        self.quaternion_convention = quaternion_convention
        self.address = address
        if isinstance(formats, dict):
            fmt_by_address = {int(a): as_format(f) for a, f in formats.items()}
        else:
            birds = range(1, (n_birds or 1) + 1) if group else [address]
            fmt_by_address = {a: as_format(formats) for a in birds}
        if not group and len(fmt_by_address) != 1:
            raise ValueError("without group mode a stream carries one bird's format")
        self.formats = fmt_by_address
        # Lookup by address byte: record length (0 = not a configured bird).
        self._length_of = np.zeros(256, np.int64)
        for a, f in fmt_by_address.items():
            self._length_of[a & 0xFF] = record_length(f, group=group, button=button)
        self._lengths = sorted({int(v) for v in self._length_of if v})
        self._distinct = list(dict.fromkeys(fmt_by_address.values()))
        self._format_index = np.full(256, -1, np.int64)
        for a, f in fmt_by_address.items():
            self._format_index[a & 0xFF] = self._distinct.index(f)
        # One record length: a chunk of whole, clean records can skip the general framing.
        self._single = self._lengths[0] if len(self._lengths) == 1 else 0
        self._arange = np.arange(0)
        # The unfinished tail is empty or one partial record: its only phasing byte is its first,
        # so one arrival time (its first byte's) is all it needs.
        self._tail = b""
        self._tail_time = np.nan
        self._offset = 0  # stream offset of the tail's first byte
        self.resyncs = 0
        self.dropped_bytes = 0
        self.bad_records = 0
        self.records = 0

    @property
    def pending_bytes(self) -> int:
        return len(self._tail)

    def reset(self) -> None:
        """Forget any unfinished record (after a flush or reconnect)."""
        self._offset += len(self._tail)
        self._tail = b""
        self._tail_time = np.nan

    def feed(self, data: bytes, arrival_time: float | None = None) -> DecodedRecords:
        """Records completed by `data` (bytes arrived at `arrival_time`), in stream order."""
        return self.decode(self.frame(data, arrival_time))

    def flush(self) -> DecodedRecords:
        """Decide the unfinished tail as if no more bytes were coming (after a POINT reply with
        mixed record lengths, where a short record could still be the start of a longer one)."""
        return self.decode(self.frame_flush())

    def frame(self, data: bytes, arrival_time: float | None = None) -> FramedRecords:
        """Like `feed`, without decoding poses: the records completed by `data`, framed."""
        if not isinstance(data, bytes):
            data = as_u8(data).tobytes()
        t = np.nan if arrival_time is None else float(arrival_time)
        n_tail = len(self._tail)
        buf = self._tail + data if n_tail else data
        return self._frame(buf, _Arrivals(n_tail, self._tail_time, t), final=False)

    def frame_chunks(self, chunks: list[bytes], arrival_times: list[float]) -> FramedRecords:
        """`frame` for several reads at once (each with its own arrival time): the same records and
        times as framing them one by one when the stream is clean, at the cost of one call."""
        if len(chunks) == 1:
            return self.frame(chunks[0], arrival_times[0])
        n_tail = len(self._tail)
        buf = b"".join([self._tail, *chunks])
        ends = np.cumsum([len(c) for c in chunks])
        times = np.asarray(arrival_times, float)
        return self._frame(buf, _Arrivals(n_tail, self._tail_time, times[-1], ends, times), final=False)

    def frame_flush(self) -> FramedRecords:
        """Like `flush`, without decoding poses."""
        return self._frame(self._tail, _Arrivals(len(self._tail), self._tail_time, self._tail_time), final=True)

    def _aranged(self, k: int) -> np.ndarray:
        if len(self._arange) < k:
            self._arange = np.arange(max(k, 2 * len(self._arange), 64), dtype=np.int64)
        return self._arange[:k]

    def _frame(self, data: bytes, arrivals: "_Arrivals", final: bool) -> FramedRecords:
        buf = np.frombuffer(data, np.uint8)
        n = len(buf)
        L = self._single
        if L and not final and n:
            # Fast path: whole records back to back from byte 0, then at most one partial record.
            heads = buf[::L]
            if heads.min() >= PHASE_BIT and np.count_nonzero(buf >= PHASE_BIT) == len(heads):
                k = n // L
                if self.group:
                    addr = buf[L - 1:k * L:L]
                    ok = k == 0 or self._length_of[addr].min() == L
                else:
                    ok = True
                if ok:
                    starts = self._aranged(k) * L
                    self._tail = data[k * L:]
                    self._tail_time = arrivals.at_index(k * L)
                    times = arrivals.at(starts)
                    addresses = addr.astype(np.int64) if self.group else np.full(k, self.address, np.int64)
                    out = FramedRecords(buf, starts, L, addresses, self._offset + starts, times, True)
                    self._offset += k * L
                    self.records += k
                    return out
        return self._frame_general(data, buf, arrivals, final)

    def _frame_general(self, data: bytes, buf: np.ndarray, arrivals: "_Arrivals", final: bool) -> FramedRecords:
        n = len(buf)
        phase = buf >= PHASE_BIT
        starts = np.flatnonzero(phase)
        # A record runs from its phasing byte to at most the next one (inner bytes have bit 7
        # clear); an undamaged stream fills that gap exactly, garbage makes it longer.
        gap = np.diff(np.append(starts, n))
        exact = np.zeros(len(starts), np.int64)
        longest = np.zeros(len(starts), np.int64)
        for L in self._lengths:  # a handful of distinct lengths at most
            fits = L <= gap
            if self.group:
                fits &= self._length_of[buf[np.minimum(starts + L - 1, n - 1)]] == L
            exact[fits & (gap == L)] = L
            longest[fits] = L
        acc_len = np.where(exact > 0, exact, longest)
        accepted = acc_len > 0
        # The last start may be a record still arriving (or, with mixed lengths, a short record
        # that could be a longer one's beginning): keep it for the next chunk.
        keep_from = n
        if len(starts) and not final and gap[-1] < self._lengths[-1]:
            keep_from = int(starts[-1])
            accepted[-1] = False
            considered = slice(0, len(starts) - 1)
        else:
            considered = slice(0, len(starts))
        self.bad_records += int(np.count_nonzero(~accepted[considered]))
        accepted_starts, acc_l = starts[accepted], acc_len[accepted]
        # Bytes covered by no accepted record (before the kept tail) are dropped; each maximal
        # run of them is one resync.
        # Accepted records never overlap, so their starts (and ends) are distinct indices.
        opened = np.zeros(keep_from + 1, np.int64)
        opened[accepted_starts] = 1
        closed = np.zeros(keep_from + 1, np.int64)
        closed[accepted_starts + acc_l] = 1
        lost = np.cumsum(opened[:keep_from] - closed[:keep_from]) <= 0
        n_lost = int(np.count_nonzero(lost))
        if n_lost:
            self.dropped_bytes += n_lost
            self.resyncs += int(lost[0]) + int(np.count_nonzero(lost[1:] & ~lost[:-1]))
        times = arrivals.at(accepted_starts)
        if self.group:
            addresses = buf[accepted_starts + acc_l - 1].astype(np.int64)
        else:
            addresses = np.full(len(accepted_starts), self.address, np.int64)
        out = FramedRecords(buf, accepted_starts, acc_l, addresses,
                            self._offset + accepted_starts.astype(np.int64), times)
        self.records += len(accepted_starts)
        self._offset += keep_from
        self._tail = data[keep_from:]
        self._tail_time = arrivals.at_index(keep_from)
        return out

    def decode(self, framed: FramedRecords) -> DecodedRecords:
        """Poses of framed records (one vectorised decode per distinct format)."""
        k = len(framed)
        if k == 0:
            return DecodedRecords.empty(self.button)
        rotations = np.empty((k, 3, 3))
        positions = np.empty((k, 3))
        valid = np.empty(k, bool)
        clipped = np.empty(k, bool)
        buttons = np.zeros(k, np.uint8) if self.button else None
        if self.group and len(self._distinct) > 1:
            kind = self._format_index[framed.addresses]
            groups = [(f, kind == i) for i, f in enumerate(self._distinct)]
        else:
            groups = [(self._distinct[0], slice(None))]
        for fmt, sel in groups:
            L = record_length(fmt, group=self.group, button=self.button)
            if isinstance(sel, slice):
                rec = framed.record_bytes(L)
            else:
                st = framed.starts[sel]
                if len(st) == 0:
                    continue
                rec = framed.buffer[st[:, None] + np.arange(L)]
            r, p, v, c = decode_block(fmt, rec, scale_inches=self.scale_inches,
                                      quaternion_convention=self.quaternion_convention)
            rotations[sel], positions[sel], valid[sel], clipped[sel] = r, p, v, c
            if self.button:
                buttons[sel] = rec[:, fmt.n_data_bytes]
        return DecodedRecords(framed.addresses, rotations, positions, valid, framed.offsets,
                              framed.times, buttons, clipped)
