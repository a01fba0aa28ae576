"""EXAMINE VALUE / CHANGE VALUE parameters: reply and data lengths, and the values they carry (protocol.md §3).
"""

from __future__ import annotations

from dataclasses import dataclass

from flockcal.drivers.commands import Command
from flockcal.drivers.words import as_u8, pack_words


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
    b = as_u8(data)
    return int(b[0]) + int(b[1]) / 100.0


def software_revision_bytes(rev: float) -> bytes:
    major = int(rev)
    return bytes([major, int(round((rev - major) * 100))])
