"""Host → bird command bytes, the data bytes each takes, and FBB addressing (protocol.md §2).

A command goes to one bird of a flock behind an RS232 TO FBB prefix; `format_command` and friends
build the bytes for a given address and addressing mode.
"""

from __future__ import annotations

from enum import IntEnum

from flockcal.drivers.records import FORMATS, RecordFormat, as_format


class Command(IntEnum):
    """Command bytes host → bird (protocol.md §2)."""

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
