"""The Flock's data records: the seven formats, and poses ↔ record bytes, vectorised over records.

Conventions (protocol.md §4–5): the transmitter frame (+Z down); R = Rz(A)·Ry(E)·Rx(R) maps sensor →
transmitter; the bird sends M = Rᵀ column by column; its quaternion is M's, scalar first. Rotation maths
is flockcal.rotations'; this module only packs and unpacks words.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flockcal.drivers.words import angle_to_word, as_u8, decode_words, encode_words, to_word
from flockcal.rotations import as_euler, as_flock_quat, from_euler, from_flock_quat, nearest_rotation

INCH = 0.0254  # metres


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
        parts.append(to_word(np.asarray(positions) / INCH, 32768.0 / scale_inches))
    if fmt.orientation == "angles":
        parts.append(angle_to_word(as_euler(rotations)))
    elif fmt.orientation == "matrix":
        # M = Rᵀ sent column by column is R row by row.
        parts.append(to_word(np.asarray(rotations).reshape(n, 9), 32768.0))
    elif fmt.orientation == "quaternion":
        q = as_flock_quat(np.asarray(rotations), quaternion_convention)
        parts.append(to_word(q, 32768.0))
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
    rec = as_u8(records)
    rec = rec.reshape(-1, record_length(fmt, group=group, button=button))
    words = decode_words(rec[:, :fmt.n_data_bytes])
    rotations, positions = poses_from_words(fmt, words, scale_inches, quaternion_convention)
    addresses = rec[:, -1].astype(np.int64) if group else None
    return rotations, positions, addresses


def saturated_records(fmt: RecordFormat | str, records) -> np.ndarray:
    """(n,) True where a record's data words are all zero: the bird's 'no valid data' record."""
    fmt = as_format(fmt)
    rec = as_u8(records).reshape(len(records), -1)[:, :fmt.n_data_bytes]
    return ~np.any(rec & 0x7F, axis=1)


def poses_from_words(fmt: RecordFormat | str, words: np.ndarray, scale_inches: float = 36.0,
                     quaternion_convention: str = "fob") -> tuple[np.ndarray, np.ndarray]:
    """Data words (n, fmt.n_words) → (rotations (n,3,3), positions (n,3) m): the decoding every reader of
    records uses (the live reader, replay, the service's frame log), so each gives the same floats."""
    fmt = as_format(fmt)
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
    return decode_block_words(fmt, records, scale_inches=scale_inches, quaternion_convention=quaternion_convention)[1:]


def decode_block_words(fmt: RecordFormat | str, records: np.ndarray, *, scale_inches: float = 36.0,
                       quaternion_convention: str = "fob") -> tuple[np.ndarray, ...]:
    """`decode_block` with the data words (n, fmt.n_words) int32 the poses came from, first."""
    fmt = as_format(fmt)
    data = records[:, :fmt.n_data_bytes]
    words = decode_words(data)
    rotations, positions = poses_from_words(fmt, words, scale_inches, quaternion_convention)
    clipped = position_clipped(fmt, words)
    valid = np.any(words, axis=1) & ~clipped
    return words, rotations, positions, valid, clipped
