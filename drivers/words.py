"""The Flock's 16-bit words on the wire: 14-bit record words with phasing bits, and plain command words.

A record word travels as two 7-bit bytes, LS byte first, bits 1..0 dropped; the first byte of a record
carries the phasing bit (protocol.md §4). Command and reply words are plain 16-bit, LS byte first.
"""

from __future__ import annotations

import numpy as np

PHASE_BIT = 0x80


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
    b = as_u8(data).astype(np.int32)
    w = ((b[..., 1::2] & 0x7F) << 9) | ((b[..., 0::2] & 0x7F) << 2)
    return w - ((w & 0x8000) << 1)


def pack_words(values) -> bytes:
    """Command data words: plain 16-bit two's complement, LS byte first, no phasing bits."""
    v = np.asarray(values, dtype=np.int64).reshape(-1) & 0xFFFF
    return np.stack([v & 0xFF, v >> 8], axis=-1).astype(np.uint8).tobytes()


def unpack_words(data, *, signed: bool = True) -> np.ndarray:
    """Reply words (LS byte first, no phasing bits) → int array."""
    b = as_u8(data).astype(np.int64)
    w = b[0::2] | (b[1::2] << 8)
    return w - ((w & 0x8000) << 1) if signed else w


def as_u8(data) -> np.ndarray:
    """Bytes (or anything array-like) as a uint8 array, without a copy for bytes."""
    if isinstance(data, (bytes, bytearray, memoryview)):
        return np.frombuffer(data, dtype=np.uint8)
    return np.asarray(data, dtype=np.uint8)


def to_word(x: np.ndarray, per_unit: float) -> np.ndarray:
    """Real values → transmitted words: rounded to the nearest multiple of 4, saturated."""
    s = np.rint(np.asarray(x, dtype=float) * (per_unit / 4.0)) * 4.0
    return np.clip(s, -32768, 32764).astype(np.int64)


def angle_to_word(a: np.ndarray) -> np.ndarray:
    """Angles (radians) → transmitted words, 180° = 32768."""
    # ±180° wraps (0x8000 is −180°), so wrap instead of saturating.
    s = np.rint(np.asarray(a, dtype=float) * (8192.0 / np.pi)).astype(np.int64) * 4
    return ((s + 32768) % 65536) - 32768
