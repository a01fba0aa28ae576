"""The frame log's blocks: a batch of frames as the tracker's own 16-bit words, delta-coded and deflated,
decoding to the very float64 values that were logged: the words the reader decoded them from when the
frames carry them (`Frames.words`), else words worked out from the poses; each checked when written, and a
sensor-frame no word pattern reproduces is kept whole. About 7x smaller than the fixed records of version 1.

A block is a 20-byte head (b"FB", codec, 0, frames u32, payload bytes u32, payload CRC-32, head CRC-32)
and a zlib payload. Codec RECORDS holds version-1 records (frames that come from no tracker, e.g. a take
fed in by a test); codec WORDS holds (all little-endian, in this order): the record format's command byte
and the position scale in inches (u8 each); the times (n f8, byte planes); the valid flags (n·m bits);
the words ÷ 4 as int16 per sensor and word over the block's frames (a matrix's third row as its difference
from the cross product of the first two, each series as its first value then frame-to-frame steps, zigzag,
low then high byte planes); the count of sensor-frames kept whole (u32), their flat indices (u32 each),
rotations (9 f8 each) and positions (3 f8 each).
"""

from __future__ import annotations

import struct
import zlib

import numpy as np

from flockcal.drivers.records import FORMAT_BY_COMMAND, FORMATS, RecordFormat, as_format, data_words, poses_from_words
from flockcal.frames import Frames, TrackerWords

HEAD = struct.Struct("<2sBBIIII")
SYNC = b"FB"
RECORDS, WORDS = 0, 1
LEVEL = 3  # zlib: 6 saved 2.6 % more bytes for 1.6x its time, 9 another 1 % for 4x
# Formats that carry a whole pose, most words first: a log of position/matrix records is decoded by the
# matrix words, and so on. Scales: the simulator's 72 in, a real flock's default 36 in.
CANDIDATES = tuple((FORMATS[name], scale) for name in ("position_matrix", "position_quaternion", "position_angles")
                   for scale in (72, 36))
_WORD_FORMATS = {fmt.name for fmt, _ in CANDIDATES}
_POSITION = as_format("position")  # a pose format's first three words decode as this one's
# A codec that has to keep more than this share of a block's sensor-frames whole is the wrong one.
WRONG_CODEC = 1 / 16
NO_CODEC = 1 / 4  # ... and with none better than this, the block is stored as records


def record_dtype(m: int) -> np.dtype:
    """The version-1 record of m sensors: what a block decodes to."""
    return np.dtype([("time", "<f8"), ("valid", "u1", (m,)), ("rot", "<f8", (m, 3, 3)), ("pos", "<f8", (m, 3))])


def records_frames(rec: np.ndarray) -> Frames:
    """Version-1 records as they were stored: `valid` keeps the stored 0/1 flags (any other byte is damage,
    which framelog.sanitize judges)."""
    return Frames(rec["time"], rec["rot"], rec["pos"], rec["valid"])


class BlockError(ValueError):
    """A block whose bytes do not decode (damaged on disk)."""


# --- encoding ---------------------------------------------------------------------------------------
def _same(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Bitwise equality over each row's trailing axes (−0.0 is not 0.0, and NaN is itself)."""
    a = np.ascontiguousarray(a).view(np.uint64).reshape(len(a), -1)
    b = np.ascontiguousarray(b).view(np.uint64).reshape(len(b), -1)
    return (a == b).all(axis=1)


def _words_for(fmt: RecordFormat, scale: int, R: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(words (k, fmt.n_words), found (k,), direct (k,)): words that decode to exactly R (k,3,3) and p (k,3),
    where found; `direct` where the re-encoded words did, before any neighbour was tried.

    The poses are the tracker's own decoding of its words, so re-encoding them mostly gives those words
    back; a matrix made orthonormal after decoding (`nearest_rotation`) may come back one step off in
    one or two of its nine words, so those words' neighbours are tried as well: first the likeliest (`_guesses`),
    then, for what they miss, every neighbour one step away in one word, the likeliest two-word step, and every
    neighbour one step away in two words."""
    with np.errstate(invalid="ignore", over="ignore"):
        w = data_words(fmt, R, p, scale_inches=scale)
        dR, dp = poses_from_words(fmt, w, scale)
    found = _same(dR, R) & _same(dp, p)
    direct = found.copy()
    if fmt.orientation == "matrix" and not found.all() and found.sum() >= len(found) // 2:
        for tries in (lambda miss: _guesses(w[miss], R[miss])[:, :2], lambda miss: _neighbours(w[miss], 1),
                      lambda miss: _guesses(w[miss], R[miss])[:, 2:], lambda miss: _neighbours(w[miss], 2)):
            miss = np.flatnonzero(~found)
            if not len(miss):
                break
            cand = tries(miss)  # (f, c, k)
            f, c, k = cand.shape
            with np.errstate(invalid="ignore", over="ignore"):
                cR, cp = poses_from_words(fmt, cand.reshape(f * c, k), scale)
            hit = (_same(cR, np.repeat(R[miss], c, axis=0)) & _same(cp, np.repeat(p[miss], c, axis=0))).reshape(f, c)
            got = hit.any(axis=1)
            w[miss[got]] = cand[got, hit[got].argmax(axis=1)]
            found[miss[got]] = True
    return w, found, direct


def _sample_found(found: np.ndarray, direct: np.ndarray, pick: np.ndarray) -> np.ndarray | None:
    """What `_words_for` of the rows `pick` alone would find, read off its result for all rows (each row's
    neighbours are tried on their own), or None where the two would differ: the neighbours are tried only
    when half the rows came back directly, and the sample and the whole may fall either side of that."""
    part = direct[pick]
    if (part.sum() >= len(part) // 2) != (direct.sum() >= len(direct) // 2):
        return None
    return found[pick]


def _guesses(w: np.ndarray, R: np.ndarray) -> np.ndarray:
    """(f, 3, 12) the likeliest words of each row's rotation R (f,3,3) near its re-encoded words w (f,12): the
    two matrix words whose unrounded value lies nearest a rounding boundary, each stepped across it, then both.
    A word the orthonormalisation moved past half a step rounds to its neighbour on the far side: the one the
    value's remainder points to. About one sensor-frame in five needs a neighbour (16 birds, 144 Hz); a guess
    finds nearly all of them, where trying each of the 18 (or 144) neighbours decoded every one."""
    rest = R.reshape(len(R), 9) * 8192.0 - w[:, 3:12] / 4.0  # in steps of 4, within ±1/2 of the word sent
    order = np.argsort(-np.abs(rest), axis=1, kind="stable")[:, :2]
    step = np.where(np.take_along_axis(rest, order, axis=1) >= 0, 4, -4)
    rows = np.arange(len(w))[:, None]
    out = np.repeat(w[:, None, :], 3, axis=1)
    out[rows, 0, 3 + order[:, :1]] += step[:, :1]
    out[rows, 1, 3 + order[:, 1:]] += step[:, 1:]
    out[rows, 2, 3 + order] += step
    return np.clip(out, -32768, 32764)


def _neighbours(w: np.ndarray, span: int) -> np.ndarray:
    """(f, c, 12) position/matrix words one step (±4) away from each row in one (`span` 1) or two of its nine
    matrix words."""
    return np.clip(w[:, None, :] + _STEPS[span][None], -32768, 32764)


def _steps(span: int) -> np.ndarray:
    if span == 1:
        steps = np.zeros((18, 12), np.int64)
        for e in range(9):
            steps[2 * e, 3 + e], steps[2 * e + 1, 3 + e] = 4, -4
        return steps
    rows = []
    for a in range(9):
        for b in range(a + 1, 9):
            for sa in (4, -4):
                for sb in (4, -4):
                    r = np.zeros(12, np.int64)
                    r[3 + a], r[3 + b] = sa, sb
                    rows.append(r)
    return np.array(rows)


_STEPS = {span: _steps(span) for span in (1, 2)}


class Encoder:
    """Writes blocks; picks each one's codec: the last block's while it fits, else the first candidate that
    reproduces a sample of the block's poses, else records (for the next RETRY blocks: frames from no
    tracker stay so)."""

    SAMPLE = 64
    RETRY = 32

    def __init__(self):
        self.codec: tuple | None = None  # the last block's (format, scale)
        self._records_left = 0

    def block(self, times: np.ndarray, R: np.ndarray, p: np.ndarray, valid: np.ndarray,
              words: TrackerWords | None = None) -> bytes:
        """A block (head and payload) of n frames: times (n,), rotations (n,m,3,3), positions (n,m,3), valid (n,m);
        `words`, the data words the poses were decoded from (frames from a tracker's reader), are stored as
        they came, with no search."""
        times = np.ascontiguousarray(times, dtype="<f8")
        valid = np.asarray(valid, dtype=bool)
        n, m = valid.shape
        R, p = np.asarray(R, dtype=float), np.asarray(p, dtype=float)
        ok = np.flatnonzero(valid.reshape(-1))
        Rf, pf = R.reshape(n * m, 3, 3)[ok], p.reshape(n * m, 3)[ok]
        carried = self._carried(words, ok, Rf, pf) if words is not None else None
        if carried is not None:
            payload = _words_payload(*carried[0], times, valid, ok, carried[1], carried[2], Rf, pf, m)
            if payload is not None:
                self.codec = carried[0]
                return _block(WORDS, n, payload)
        codec, known = self._choose(Rf, pf)
        if codec is not None:
            w, found = known if known is not None else _words_for(*codec, Rf, pf)[:2]
            payload = None if len(found) - found.sum() > NO_CODEC * len(found) else \
                _words_payload(*codec, times, valid, ok, w, found, Rf, pf, m)
            if payload is not None:
                self.codec = codec
                return _block(WORDS, n, payload)
        self.codec, self._records_left = None, self.RETRY
        return _block(RECORDS, n, _records_payload(times, R, p, valid))

    def _carried(self, words: TrackerWords, ok: np.ndarray, Rf: np.ndarray, pf: np.ndarray
                 ) -> tuple[tuple, np.ndarray, np.ndarray] | None:
        """((format, scale), the valid sensor-frames' words, which of them decode to the very poses given)
        from the words the frames carry, when their format is one a block stores and a sample of SAMPLE of
        their rotations decodes to the very rotations given; None otherwise, and the block's words are worked
        out from the poses. Positions are checked one and all (a multiplication each); rotations on a sample:
        the reader decoded them from these very words, so the sample guards the hand-over (frames and words
        out of step), which it would find in any row."""
        fmt = FORMAT_BY_COMMAND.get(int(words.command))
        scale = int(words.scale_inches)
        if fmt is None or fmt.name not in _WORD_FORMATS or scale != words.scale_inches or not 0 < scale < 256:
            return None
        w = words.words.reshape(-1, fmt.n_words)[ok]
        with np.errstate(invalid="ignore", over="ignore"):
            found = _same(poses_from_words(_POSITION, w[:, :3], scale)[1], pf)
            pick = np.linspace(0, len(ok) - 1, min(self.SAMPLE, len(ok))).astype(int)
            sample = _same(poses_from_words(fmt, w[pick], scale)[0], Rf[pick])
        if not sample.all() or len(found) - found.sum() > WRONG_CODEC * len(found):
            return None
        return (fmt, scale), w, found

    def _choose(self, Rf: np.ndarray, pf: np.ndarray) -> tuple[tuple | None, tuple | None]:
        """(the codec, and the block's (words, found) in it when they were worked out on the way)."""
        if not len(Rf):
            return self.codec or CANDIDATES[0], None
        if self._records_left > 0:
            self._records_left -= 1
            return None, None
        pick = np.linspace(0, len(Rf) - 1, min(self.SAMPLE, len(Rf))).astype(int)
        for cand in ([self.codec] if self.codec else []) + [c for c in CANDIDATES if c != self.codec]:
            if cand == self.codec:
                # The last block's codec mostly fits again: the whole block's words, the sample's read off them.
                w, found, direct = _words_for(*cand, Rf, pf)
                sample = _sample_found(found, direct, pick)
                if sample is None:
                    sample = _words_for(*cand, Rf[pick], pf[pick])[1]
                if len(sample) - sample.sum() <= WRONG_CODEC * len(sample):
                    return cand, (w, found)
                continue
            found = _words_for(*cand, Rf[pick], pf[pick])[1]
            if len(found) - found.sum() <= WRONG_CODEC * len(found):
                return cand, None
        return None, None


def _block(codec: int, n: int, payload: bytes) -> bytes:
    data = zlib.compress(payload, LEVEL)
    head = HEAD.pack(SYNC, codec, 0, n, len(data), zlib.crc32(data), 0)
    return head[:-4] + struct.pack("<I", zlib.crc32(head[:-4])) + data


def _records_payload(times, R, p, valid) -> bytes:
    return np.rec.fromarrays([times, valid, R, p], dtype=record_dtype(valid.shape[1])).tobytes()


def _words_payload(fmt, scale, times, valid, ok, w, found, Rf, pf, m) -> bytes | None:
    n = len(times)
    k = fmt.n_words
    grid = np.zeros((n * m, k), np.int64)
    grid[ok[found]] = w[found]
    series = (grid >> 2).reshape(n, m, k).transpose(1, 2, 0)  # (m, k, n): one word of one sensor over time
    if fmt.orientation == "matrix":
        series = _predict_third_row(series, -1)
    steps = np.diff(series, axis=-1, prepend=0)
    zig = (steps << 1) ^ (steps >> 63)
    if zig.size and zig.max() > 0xFFFF:  # only words no tracker sends step this far: keep the records
        return None
    kept = ok[~found]
    parts = [bytes((fmt.command, scale)), _planes(times.view(np.uint8).reshape(n, 8)),
             np.packbits(valid.reshape(-1)).tobytes(),
             (zig & 0xFF).astype(np.uint8).tobytes(), (zig >> 8).astype(np.uint8).tobytes(),
             struct.pack("<I", len(kept)), kept.astype("<u4").tobytes(),
             np.ascontiguousarray(Rf[~found], dtype="<f8").tobytes(), np.ascontiguousarray(pf[~found], dtype="<f8").tobytes()]
    return b"".join(parts)


def _planes(b: np.ndarray) -> bytes:
    """(n, 8) bytes → each byte position's n bytes in turn (the high bytes of nearby times are equal)."""
    return np.ascontiguousarray(b.T).tobytes()


def _predict_third_row(series: np.ndarray, sign: int) -> np.ndarray:
    """A rotation's third row is the cross product of its first two: the words (÷ 4, 8192 per unit) of the
    third row minus (`sign` -1) or plus (+1) the words that product predicts, for series (m, 12, n) of
    position/matrix words. Integer arithmetic and one correctly rounded division: the same on every machine."""
    out = series.copy()
    a, b = series[:, 3:6], series[:, 6:9]
    cross = np.stack([a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1], a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
                      a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]], axis=1)
    out[:, 9:12] = series[:, 9:12] + sign * np.rint(cross / 8192.0).astype(np.int64)
    return out


# --- decoding ---------------------------------------------------------------------------------------
def parse_head(head: bytes) -> tuple[int, int, int, int] | None:
    """(codec, frames, payload bytes, payload CRC) of a block head, or None when these are not one."""
    if len(head) < HEAD.size:
        return None
    sync, codec, _, n, size, crc, head_crc = HEAD.unpack(head[:HEAD.size])
    if sync != SYNC or head_crc != zlib.crc32(head[:HEAD.size - 4]) or codec not in (RECORDS, WORDS):
        return None
    return codec, n, size, crc


def decode(codec: int, n: int, m: int, data: bytes, crc: int) -> Frames:
    """A block's payload as n frames of m sensors, as stored (`records_frames`); BlockError when its bytes
    are damaged."""
    if zlib.crc32(data) != crc:
        raise BlockError("a frame log block failed its checksum")
    try:
        raw = zlib.decompress(data)
    except zlib.error as exc:
        raise BlockError(f"a frame log block does not inflate: {exc}") from None
    dt = record_dtype(m)
    if codec == RECORDS:
        if len(raw) != n * dt.itemsize:
            raise BlockError("a frame log block holds the wrong number of records")
        return records_frames(np.frombuffer(raw, dtype=dt).copy())
    try:
        return _decode_words(raw, n, m)
    except (ValueError, KeyError, IndexError) as exc:
        raise BlockError(f"a frame log block does not decode: {exc}") from None


class _Cursor:
    """Reads a payload's parts in turn."""

    def __init__(self, raw: bytes):
        self.raw, self.at = memoryview(raw), 0

    def take(self, count: int, dtype) -> np.ndarray:
        dtype = np.dtype(dtype)
        size = count * dtype.itemsize
        if self.at + size > len(self.raw):
            raise ValueError("it is shorter than its parts")
        out = np.frombuffer(self.raw[self.at:self.at + size], dtype)
        self.at += size
        return out


def _decode_words(raw: bytes, n: int, m: int) -> Frames:
    cur = _Cursor(raw)
    command, scale = cur.take(2, np.uint8).tolist()
    fmt = FORMAT_BY_COMMAND[command]
    k = fmt.n_words
    times = np.ascontiguousarray(cur.take(8 * n, np.uint8).reshape(8, n).T).view("<f8").reshape(n)
    valid = np.unpackbits(cur.take((n * m + 7) // 8, np.uint8))[:n * m].astype(bool)
    lo = cur.take(m * k * n, np.uint8).astype(np.int64)
    zig = (lo | (cur.take(m * k * n, np.uint8).astype(np.int64) << 8)).reshape(m, k, n)
    series = np.cumsum((zig >> 1) ^ -(zig & 1), axis=-1)
    if fmt.orientation == "matrix":
        series = _predict_third_row(series, +1)
    (count,) = cur.take(1, "<u4").tolist()
    kept = cur.take(count, "<u4").astype(np.int64)
    kR = cur.take(9 * count, "<f8").reshape(count, 3, 3)
    kp = cur.take(3 * count, "<f8").reshape(count, 3)
    if cur.at != len(raw) or (count and kept.max() >= n * m):
        raise ValueError("its parts do not add up to its length")
    words = (series << 2).transpose(2, 0, 1).reshape(n * m, k)
    R = np.zeros((n * m, 3, 3))
    p = np.zeros((n * m, 3))
    coded = valid.copy()
    coded[kept] = False
    idx = np.flatnonzero(coded)
    if len(idx):
        R[idx], p[idx] = poses_from_words(fmt, words[idx], scale)
    R[kept], p[kept] = kR, kp
    return Frames(times, R.reshape(n, m, 3, 3), p.reshape(n, m, 3), valid.reshape(n, m))
