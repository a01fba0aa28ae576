"""Flock of Birds wire format: pure, vectorised conversions between bytes and numpy arrays.

Records (phasing bit, 14-bit words, group address bytes), stream framing with resync, and the
small command/reply encodings (EXAMINE/CHANGE tables, error codes, status bytes, FBB prefixes).
Conventions (fob-protocol.md §4–5): FOB transmitter frame (+Z down); R = Rz(A)·Ry(E)·Rx(R) maps
sensor → transmitter; the bird sends M = Rᵀ column by column; q_FOB is M's quaternion (q0 scalar).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from flockcal.rotations import as_euler, as_flock_quat, from_euler, from_flock_quat, nearest_rotation

INCH = 0.0254  # metres
PHASE_BIT = 0x80

# ---------------------------------------------------------------------------------------------
# Record formats


@dataclass(frozen=True)
class RecordFormat:
    """One data-record format: its command byte, status-word code (bits 4..1) and word count."""

    name: str
    command: int
    status_code: int
    n_words: int
    position: bool
    orientation: str  # "" | "angles" | "matrix" | "quaternion"

    @property
    def n_data_bytes(self) -> int:
        return 2 * self.n_words


FORMATS: dict[str, RecordFormat] = {
    f.name: f
    for f in (
        RecordFormat("position", 0x56, 1, 3, True, ""),
        RecordFormat("angles", 0x57, 2, 3, False, "angles"),
        RecordFormat("matrix", 0x58, 3, 9, False, "matrix"),
        RecordFormat("position_angles", 0x59, 4, 6, True, "angles"),
        RecordFormat("position_matrix", 0x5A, 5, 12, True, "matrix"),
        RecordFormat("quaternion", 0x5C, 7, 4, False, "quaternion"),
        RecordFormat("position_quaternion", 0x5D, 8, 7, True, "quaternion"),
    )
}
FORMAT_BY_COMMAND: dict[int, RecordFormat] = {f.command: f for f in FORMATS.values()}
FORMAT_BY_STATUS: dict[int, RecordFormat] = {f.status_code: f for f in FORMATS.values()}
DEFAULT_FORMAT = FORMATS["position_angles"]  # power-up default [MAN p38]

ORIENTATION_WORDS = {"": 0, "angles": 3, "matrix": 9, "quaternion": 4}


def as_format(fmt: RecordFormat | str | int) -> RecordFormat:
    """A RecordFormat from itself, its name, or its command byte."""
    if isinstance(fmt, RecordFormat):
        return fmt
    if isinstance(fmt, str):
        return FORMATS[fmt]
    return FORMAT_BY_COMMAND[int(fmt)]


def record_length(fmt: RecordFormat | str, *, group: bool, button: bool = False,
                  metal: bool = False) -> int:
    """Bytes in one record: 2·words + button byte + metal byte + group address byte."""
    return as_format(fmt).n_data_bytes + int(button) + int(metal) + int(group)


# ---------------------------------------------------------------------------------------------
# 14-bit words


def encode_words(words) -> np.ndarray:
    """Words (..., k) → record bytes (..., 2k) uint8, LS byte first, phasing bit on byte 0.

    Bits 1..0 of each word are not transmitted. A 1-D input is one record.
    """
    w = np.asarray(words).astype(np.int64) & 0xFFFF
    out = np.empty(w.shape[:-1] + (2 * w.shape[-1],), dtype=np.uint8)
    out[..., 0::2] = (w >> 2) & 0x7F
    out[..., 1::2] = (w >> 9) & 0x7F
    out[..., 0] |= PHASE_BIT
    return out


def decode_words(data) -> np.ndarray:
    """Record bytes (..., 2k) → signed words (..., k) int32 (multiples of 4, −32768..32764)."""
    b = _as_u8(data).astype(np.int32)
    w = ((b[..., 1::2] & 0x7F) << 9) | ((b[..., 0::2] & 0x7F) << 2)
    return w - ((w & 0x8000) << 1)


def pack_words(values) -> bytes:
    """Command data words: plain 16-bit two's complement, LS byte first, no phasing bits."""
    v = np.asarray(values, dtype=np.int64).reshape(-1) & 0xFFFF
    return np.stack([v & 0xFF, v >> 8], axis=-1).astype(np.uint8).tobytes()


def unpack_words(data, *, signed: bool = True) -> np.ndarray:
    """Reply words (LS byte first, no phasing bits) → int array."""
    b = _as_u8(data).astype(np.int64)
    w = b[0::2] | (b[1::2] << 8)
    return w - ((w & 0x8000) << 1) if signed else w


def _as_u8(data) -> np.ndarray:
    if isinstance(data, (bytes, bytearray, memoryview)):
        return np.frombuffer(data, dtype=np.uint8)
    return np.asarray(data, dtype=np.uint8)


def _to_word(x: np.ndarray, per_unit: float) -> np.ndarray:
    """Real values → transmitted words: rounded to the nearest multiple of 4, saturated."""
    s = np.rint(np.asarray(x, dtype=float) * (per_unit / 4.0)) * 4.0
    return np.clip(s, -32768, 32764).astype(np.int64)


def _angle_to_word(a: np.ndarray) -> np.ndarray:
    # ±180° wraps (0x8000 is −180°), so wrap instead of saturating.
    s = np.rint(np.asarray(a, dtype=float) * (8192.0 / np.pi)).astype(np.int64) * 4
    return ((s + 32768) % 65536) - 32768


# ---------------------------------------------------------------------------------------------
# Records


def encode_records(fmt: RecordFormat | str, rotations, positions, *, scale_inches: float = 36.0,
                   addresses=None, buttons=None, quaternion_convention: str = "fob") -> bytes:
    """Poses → the bytes a bird sends, one record per row.

    rotations (n,3,3) body→transmitter, positions (n,3) metres (clipped at full scale like the
    bird). `addresses` (n,) appends the group-mode address byte; `buttons` (n,) the button byte.
    """
    fmt = as_format(fmt)
    rotations = np.asarray(rotations, dtype=float).reshape(-1, 3, 3)
    positions = np.asarray(positions, dtype=float).reshape(-1, 3)
    words = data_words(fmt, rotations, positions, scale_inches=scale_inches,
                       quaternion_convention=quaternion_convention)
    return assemble_records(words, addresses=addresses, buttons=buttons).tobytes()


def data_words(fmt: RecordFormat | str, rotations: np.ndarray, positions: np.ndarray, *,
               scale_inches: float = 36.0, quaternion_convention: str = "fob") -> np.ndarray:
    """Poses (n,3,3), (n,3) → transmitted words (n, fmt.n_words) int64."""
    fmt = as_format(fmt)
    n = len(positions) if fmt.position else len(rotations)
    parts = []
    if fmt.position:
        parts.append(_to_word(np.asarray(positions) / INCH, 32768.0 / scale_inches))
    if fmt.orientation == "angles":
        parts.append(_angle_to_word(as_euler(rotations)))
    elif fmt.orientation == "matrix":
        # M = Rᵀ sent column by column is R row by row.
        parts.append(_to_word(np.asarray(rotations).reshape(n, 9), 32768.0))
    elif fmt.orientation == "quaternion":
        q = as_flock_quat(np.asarray(rotations), quaternion_convention)
        parts.append(_to_word(q, 32768.0))
    return np.concatenate(parts, axis=1)


def assemble_records(words: np.ndarray, *, addresses=None, buttons=None) -> np.ndarray:
    """Words (n, k) → record bytes (n, L) uint8 with optional button and address bytes."""
    rec = encode_words(words)
    extra = []
    if buttons is not None:
        extra.append(np.broadcast_to(np.asarray(buttons, dtype=np.uint8) & 0x7F, (len(rec),)))
    if addresses is not None:
        extra.append(np.broadcast_to(np.asarray(addresses, dtype=np.uint8) & 0x7F, (len(rec),)))
    if extra:
        rec = np.concatenate([rec, np.stack(extra, axis=1)], axis=1)
    return rec


def decode_records(fmt: RecordFormat | str, records, *, scale_inches: float = 36.0,
                   group: bool, button: bool = False,
                   quaternion_convention: str = "fob") -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Record bytes (n, L) → (rotations (n,3,3) body→world, positions (n,3) m, addresses (n,) | None).

    Parts a format does not carry are NaN (rotation of "position", position of "angles").
    An all-zero record (saturated/absent sensor) decodes to identity and the origin; see
    `saturated_records` to flag it.
    """
    fmt = as_format(fmt)
    rec = _as_u8(records)
    rec = rec.reshape(-1, record_length(fmt, group=group, button=button))
    words = decode_words(rec[:, :fmt.n_data_bytes])
    rotations, positions = _poses_from_words(fmt, words, scale_inches, quaternion_convention)
    addresses = rec[:, -1].astype(np.int64) if group else None
    return rotations, positions, addresses


def saturated_records(fmt: RecordFormat | str, records) -> np.ndarray:
    """(n,) True where a record's data words are all zero: the bird's 'no valid data' record."""
    fmt = as_format(fmt)
    rec = _as_u8(records).reshape(len(records), -1)[:, :fmt.n_data_bytes]
    return ~np.any(rec & 0x7F, axis=1)


def _poses_from_words(fmt: RecordFormat, words: np.ndarray, scale_inches: float,
                      quaternion_convention: str) -> tuple[np.ndarray, np.ndarray]:
    n = len(words)
    positions = np.full((n, 3), np.nan)
    rotations = np.full((n, 3, 3), np.nan)
    k = 0
    if fmt.position:
        positions = words[:, :3] * (scale_inches * INCH / 32768.0)
        k = 3
    ow = words[:, k:]
    if fmt.orientation == "angles":
        a = ow * (np.pi / 32768.0)
        rotations = from_euler(a[:, 0], a[:, 1], a[:, 2])
    elif fmt.orientation == "matrix":
        m = ow.reshape(n, 3, 3) / 32768.0
        zero = ~np.any(ow, axis=1)
        m[zero] = np.eye(3)
        rotations = nearest_rotation(m)
    elif fmt.orientation == "quaternion":
        q = ow / 32768.0
        q[~np.any(ow, axis=1)] = (1.0, 0.0, 0.0, 0.0)
        rotations = from_flock_quat(q, quaternion_convention)
    return rotations, positions


def quantisation_tolerance(fmt: RecordFormat | str, scale_inches: float = 36.0) -> tuple[float, float]:
    """Worst-case (rotation error rad, position error m) that quantisation alone can cause."""
    fmt = as_format(fmt)
    pos = 2.0 * scale_inches * INCH / 32768.0 * np.sqrt(3)
    step = 4.0 / 32768.0
    rot = {"": 0.0, "angles": 3 * np.pi * step, "matrix": 6 * step, "quaternion": 6 * step}
    return rot[fmt.orientation], pos if fmt.position else 0.0


# ---------------------------------------------------------------------------------------------
# Stream framing


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


def position_clipped(fmt: RecordFormat | str, words: np.ndarray) -> np.ndarray:
    """(n,) True where a position word sits at the clip limit (|word| ≥ 32764, i.e. |position| ≥
    FS·(1 − 1 step)): the sensor was beyond full scale and that position is garbage."""
    fmt = as_format(fmt)
    if not fmt.position:
        return np.zeros(len(words), bool)
    return np.abs(words[:, :3]).max(axis=1) >= 32764


def decode_block(fmt: RecordFormat | str, records: np.ndarray, *, scale_inches: float = 36.0,
                 quaternion_convention: str = "fob") -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Record bytes (n, L) of one format → (rotations, positions, valid, clipped), all (n, …).

    `valid` is False for the all-zero record (no data) and for a position clipped at full scale.
    """
    fmt = as_format(fmt)
    data = records[:, :fmt.n_data_bytes]
    words = decode_words(data)
    rotations, positions = _poses_from_words(fmt, words, scale_inches, quaternion_convention)
    clipped = position_clipped(fmt, words)
    valid = np.any(words, axis=1) & ~clipped
    return rotations, positions, valid, clipped


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
            data = _as_u8(data).tobytes()
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


# ---------------------------------------------------------------------------------------------
# Commands and replies


class Command(IntEnum):
    """Command bytes host → bird (fob-protocol.md §2)."""

    STREAM = 0x40
    STREAM_STOP = 0x3F
    POINT = 0x42
    RUN = 0x46
    SLEEP = 0x47
    SYNC = 0x41
    HEMISPHERE = 0x4C
    REFERENCE_FRAME1 = 0x48
    REFERENCE_FRAME2 = 0x72
    ANGLE_ALIGN1 = 0x4A
    ANGLE_ALIGN2 = 0x71
    BORESIGHT = 0x75
    BORESIGHT_REMOVE = 0x76
    OFFSET = 0x4B
    BUTTON_MODE = 0x4D
    BUTTON_READ = 0x4E
    METAL = 0x73
    METAL_ERROR = 0x74
    REPORT_RATE_1 = 0x51
    REPORT_RATE_2 = 0x52
    REPORT_RATE_8 = 0x53
    REPORT_RATE_32 = 0x54
    NEXT_TRANSMITTER = 0x30
    FBB_RESET = 0x2F
    EXAMINE = 0x4F
    CHANGE = 0x50
    XOFF = 0x13
    XON = 0x11
    FACTORY_TEST = 0x7A


# Data bytes that follow each fixed-length command (CHANGE depends on its parameter).
COMMAND_DATA_BYTES: dict[int, int] = {
    **{c: 0 for c in Command},
    Command.SYNC: 1, Command.HEMISPHERE: 2, Command.REFERENCE_FRAME1: 12,
    Command.REFERENCE_FRAME2: 6, Command.ANGLE_ALIGN1: 12, Command.ANGLE_ALIGN2: 6,
    Command.OFFSET: 6, Command.BUTTON_MODE: 1, Command.METAL: 2, Command.NEXT_TRANSMITTER: 1,
    Command.EXAMINE: 1,
    **{f.command: 0 for f in FORMATS.values()},
}
REPORT_RATE_DIVISORS = {Command.REPORT_RATE_1: 1, Command.REPORT_RATE_2: 2,
                        Command.REPORT_RATE_8: 8, Command.REPORT_RATE_32: 32}

ADDRESSING_MODES = {0: "normal", 1: "expanded", 3: "super_expanded"}
MAX_ADDRESS = {"normal": 14, "expanded": 30, "super_expanded": 126}


@dataclass(frozen=True)
class Parameter:
    """An EXAMINE/CHANGE parameter: reply bytes per addressing mode, CHANGE data bytes (None = read-only)."""

    number: int
    name: str
    reply: tuple[int, int, int]  # normal, expanded, super-expanded
    change: int | None

    def reply_length(self, addressing: str = "normal") -> int:
        return self.reply[("normal", "expanded", "super_expanded").index(addressing)]


def _p(number, name, reply, change):
    r = reply if isinstance(reply, tuple) else (reply,) * 3
    return Parameter(number, name, r, change)


PARAMETERS: dict[int, Parameter] = {
    p.number: p for p in (
        _p(0, "bird_status", 2, None), _p(1, "software_revision", 2, None),
        _p(2, "crystal_speed", 2, None), _p(3, "position_scaling", 2, 2),
        _p(4, "filter_on_off", 2, 2), _p(5, "dc_filter_alpha_min", 14, 14),
        _p(6, "measurement_rate_count", 2, 2), _p(7, "measurement_rate", 2, 2),
        _p(8, "data_ready_output", 1, 1), _p(9, "data_ready_character", 1, 1),
        _p(10, "error_code", 1, None), _p(11, "error_detect_mask", 1, 1),
        _p(12, "dc_filter_vm", 14, 14), _p(13, "dc_filter_alpha_max", 14, 14),
        _p(14, "sudden_output_change_lock", 1, 1), _p(15, "model_id", 10, None),
        _p(16, "expanded_error_code", 2, None), _p(17, "xyz_reference_frame", 1, 1),
        _p(18, "transmitter_mode", 1, 1), _p(19, "fbb_addressing_mode", 1, None),
        _p(20, "filter_line_frequency", 1, 1), _p(21, "fbb_address", 1, None),
        _p(22, "hemisphere", 2, 2), _p(23, "angle_align2", 6, 6),
        _p(24, "reference_frame2", 6, 6), _p(25, "bird_serial_number", 2, None),
        _p(26, "sensor_serial_number", 2, None), _p(27, "transmitter_serial_number", 2, None),
        _p(28, "metal", 10, 10), _p(29, "report_rate", 1, 1), _p(32, "fbb_host_delay", 2, 2),
        _p(35, "group_mode", 1, 1), _p(36, "flock_system_status", (14, 30, 126), None),
        _p(50, "fbb_auto_config", (5, 7, 19), 1),
    )
}
PARAMETER_BY_NAME = {p.name: p for p in PARAMETERS.values()}


def examine_reply_length(param: int, addressing: str = "normal") -> int:
    """Bytes the bird sends back to EXAMINE `param` in this addressing mode."""
    return PARAMETERS[param].reply_length(addressing)


def change_data_length(param: int) -> int | None:
    """Data bytes CHANGE VALUE `param` takes after the parameter byte (None: not changeable)."""
    return PARAMETERS[param].change


def examine_command(param: int) -> bytes:
    return bytes([Command.EXAMINE, param])


def change_command(param: int, data: bytes | int) -> bytes:
    """`P param data`; an int is sent as one byte, or as an LS-first word for 2-byte parameters."""
    n = change_data_length(param)
    if n is None:
        raise ValueError(f"parameter {param} ({PARAMETERS[param].name}) cannot be changed")
    if isinstance(data, int):
        data = bytes([data & 0xFF]) if n == 1 else pack_words([data])
    if len(data) != n:
        raise ValueError(f"CHANGE {param} takes {n} data bytes, got {len(data)}")
    return bytes([Command.CHANGE, param]) + bytes(data)


def fbb_prefix(address: int, addressing: str = "normal") -> bytes:
    """RS232 TO FBB prefix that routes the next command to `address` (b'' for address 0)."""
    if address == 0:
        return b""
    limit = MAX_ADDRESS[addressing]
    if not 1 <= address <= limit:
        raise ValueError(f"FBB address {address} is outside 1..{limit} for {addressing} addressing")
    if addressing == "super_expanded":
        return bytes([0xA0, address])
    if address <= 15:
        return bytes([0xF0 + address])
    return bytes([0xE0 + address - 16])


def format_command(fmt: RecordFormat | str, address: int = 0, addressing: str = "normal") -> bytes:
    return fbb_prefix(address, addressing) + bytes([as_format(fmt).command])


HEMISPHERES: dict[str, tuple[int, int]] = {
    "forward": (0x00, 0x00), "aft": (0x00, 0x01), "upper": (0x0C, 0x01),
    "lower": (0x0C, 0x00), "left": (0x06, 0x01), "right": (0x06, 0x00),
}
HEMISPHERE_BY_BYTES = {v: k for k, v in HEMISPHERES.items()}
_HEMISPHERE_AXIS = {0x00: 0, 0x06: 1, 0x0C: 2}


def hemisphere_bytes(name: str) -> bytes:
    """The two data bytes (axis, sign) of HEMISPHERE 'L' or CHANGE p22."""
    return bytes(HEMISPHERES[name])


def hemisphere_command(name: str, address: int = 0, addressing: str = "normal") -> bytes:
    return fbb_prefix(address, addressing) + bytes([Command.HEMISPHERE]) + hemisphere_bytes(name)


def hemisphere_vector(name: str) -> np.ndarray:
    """Unit vector of the hemisphere's direction in transmitter axes (forward = +X, lower = +Z)."""
    axis, sign = HEMISPHERES[name]
    v = np.zeros(3)
    v[_HEMISPHERE_AXIS[axis]] = -1.0 if sign else 1.0
    return v


def fold_to_hemisphere(positions: np.ndarray, name: str) -> np.ndarray:
    """What the bird reports: positions outside the hemisphere come back mirrored (p → −p)."""
    positions = np.asarray(positions, dtype=float)
    flip = positions @ hemisphere_vector(name) < 0
    return np.where(flip[..., None], -positions, positions)


ERROR_CODES: dict[int, str] = {
    0: "no error",
    1: "system RAM failure",
    2: "non-volatile storage write failure",
    3: "PCB configuration data corrupt",
    4: "transmitter configuration data corrupt",
    5: "sensor configuration data corrupt",
    6: "invalid RS232 command",
    7: "not an FBB master",
    8: "no birds accessible in device list",
    9: "bird is not initialised (auto-configure it)",
    10: "FBB receive error, intra-bird bus",
    11: "RS232 receive overrun or framing error",
    12: "FBB receive error, FBB host bus",
    13: "no FBB command response from a slave",
    14: "invalid FBB host command",
    15: "FBB run-time error",
    16: "invalid CPU speed",
    17: "no FBB data",
    18: "illegal baud rate",
    19: "slave acknowledge error",
    20: "CPU fault: intel 80186 trap (divide by zero etc.)",
    21: "CPU fault: single step",
    22: "CPU fault: breakpoint",
    23: "CPU fault: intrinsic overflow",
    24: "CPU fault: array bounds",
    25: "CPU fault: invalid op code",
    26: "CPU fault: escape op code",
    27: "CPU fault: reserved interrupt",
    28: "CRT sync error",
    29: "transmitter not accessible",
    30: "extended range transmitter not attached",
    31: "CPU time overflow (measurement rate too high)",
    32: "sensor saturated",
    33: "slave configuration error",
    34: "watchdog error",
    35: "over-temperature",
}
FATAL_ERRORS = frozenset({1, 2, 15, 16, *range(20, 28)})


def error_is_fatal(code: int) -> bool:
    return code in FATAL_ERRORS


def error_message(code: int, address: int | None = None) -> str:
    where = "" if address is None else f"bird {address} "
    kind = "fatal error" if code in FATAL_ERRORS else "error"
    return f"{where}{kind} {code}: {ERROR_CODES.get(code, 'unknown error code')}"


@dataclass(frozen=True)
class BirdStatus:
    """Bird status word (EXAMINE p0) decoded."""

    master: bool
    initialised: bool
    error: bool
    running: bool
    host_sync: bool
    expanded_addressing: bool
    crt_sync: bool
    no_sync: bool
    factory_test: bool
    xoff: bool
    sleeping: bool
    format: RecordFormat | None
    stream: bool

    @property
    def word(self) -> int:
        bits = (self.master, self.initialised, self.error, self.running, self.host_sync,
                self.expanded_addressing, self.crt_sync, self.no_sync, self.factory_test,
                self.xoff, self.sleeping)
        w = sum(int(b) << (15 - i) for i, b in enumerate(bits))
        return w | ((self.format.status_code if self.format else 0) << 1) | int(self.stream)


def decode_status_word(word: int | bytes) -> BirdStatus:
    """EXAMINE p0 reply (2 bytes LS first, or the int) → BirdStatus."""
    if not isinstance(word, int):
        word = int(unpack_words(word, signed=False)[0])
    bit = lambda i: bool(word >> i & 1)  # noqa: E731
    return BirdStatus(bit(15), bit(14), bit(13), bit(12), bit(11), bit(10), bit(9), bit(8),
                      bit(7), bit(6), bit(5), FORMAT_BY_STATUS.get((word >> 1) & 0xF), bit(0))


def encode_status_word(**flags) -> int:
    """Status word from BirdStatus field values (missing ones False/None)."""
    defaults = {f: False for f in BirdStatus.__dataclass_fields__}
    defaults["format"] = None
    defaults.update(flags)
    if isinstance(defaults["format"], str):
        defaults["format"] = FORMATS[defaults["format"]]
    return BirdStatus(**defaults).word


@dataclass(frozen=True)
class FlockStatus:
    """Flock system status (EXAMINE p36), arrays over addresses 1..N."""

    accessible: np.ndarray
    running: np.ndarray
    sensor: np.ndarray
    ert: np.ndarray
    transmitters: np.ndarray  # bits 3..0: ERT #3..#1 / ERT #0 or standard transmitter

    @property
    def addresses(self) -> np.ndarray:
        return np.arange(1, len(self.accessible) + 1)

    def running_sensors(self) -> np.ndarray:
        """Addresses that will send records in group mode."""
        return self.addresses[self.accessible & self.running & self.sensor]


def decode_flock_status(data: bytes) -> FlockStatus:
    b = _as_u8(data)
    return FlockStatus((b & 0x80) != 0, (b & 0x40) != 0, (b & 0x20) != 0, (b & 0x10) != 0, b & 0x0F)


def flock_status_byte(*, accessible: bool = True, running: bool = True, sensor: bool = True,
                      ert: bool = False, transmitters: int = 0) -> int:
    return (accessible << 7) | (running << 6) | (sensor << 5) | (ert << 4) | (transmitters & 0x0F)


def measurement_rate_word(rate_hz: float) -> int:
    """CHANGE p7 value: rate × 256 (unsigned 16-bit)."""
    return int(round(rate_hz * 256)) & 0xFFFF


def measurement_rate_from_word(word: int) -> float:
    return (word & 0xFFFF) / 256.0


def measurement_rate_from_count(count: int, crystal_mhz: float = 25.0) -> float:
    """p6 formula: rate = 1000 / (4·XTIME + 0.3), XTIME (ms) = count·(8 / MHz) / 1000."""
    return 1000.0 / (4.0 * count * (8.0 / crystal_mhz) / 1000.0 + 0.3)


def measurement_count_from_rate(rate_hz: float, crystal_mhz: float = 25.0) -> int:
    return int(round((1000.0 / rate_hz - 0.3) / 4.0 * 1000.0 * crystal_mhz / 8.0))


def software_revision(data: bytes) -> float:
    """p1 reply: byte0 integer part, byte1 fraction in hundredths (3.67 → 03 43)."""
    b = _as_u8(data)
    return int(b[0]) + int(b[1]) / 100.0


def software_revision_bytes(rev: float) -> bytes:
    major = int(rev)
    return bytes([major, int(round((rev - major) * 100))])
