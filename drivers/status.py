"""What a bird says about itself: error codes and their meaning, the bird status word and the flock's
status bytes (protocol.md §8).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flockcal.drivers.records import FORMAT_BY_STATUS, FORMATS, RecordFormat
from flockcal.drivers.words import as_u8, unpack_words


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
    b = as_u8(data)
    return FlockStatus((b & 0x80) != 0, (b & 0x40) != 0, (b & 0x20) != 0, (b & 0x10) != 0, b & 0x0F)


def flock_status_byte(*, accessible: bool = True, running: bool = True, sensor: bool = True,
                      ert: bool = False, transmitters: int = 0) -> int:
    return (accessible << 7) | (running << 6) | (sensor << 5) | (ert << 4) | (transmitters & 0x0F)
