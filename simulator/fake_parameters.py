"""The fake flock's EXAMINE VALUE replies and CHANGE VALUE effects, parameter by parameter (protocol.md §3).

`ParameterSet` is one part of `FakeFlock`, called from its command state machine under the flock's lock.
"""

from __future__ import annotations

from flockcal.drivers.hemispheres import hemisphere_bytes
from flockcal.drivers.parameters import (
    PARAMETERS, examine_reply_length, measurement_count_from_rate, measurement_rate_from_count,
    measurement_rate_from_word, measurement_rate_word, software_revision_bytes,
)
from flockcal.drivers.status import encode_status_word, flock_status_byte
from flockcal.drivers.words import pack_words, unpack_words
from flockcal.simulator.fake_units import CRYSTAL_MHZ, SOFTWARE_REVISION, Bird


class ParameterSet:
    """EXAMINE/CHANGE of FakeFlock (which holds the state these methods use)."""

    def _status_word(self, bird: Bird) -> int:
        line = next((ln for ln in self.lines if ln.home == bird.address), self.lines[0])
        return encode_status_word(
            master=bird.address == 1, initialised=self.initialised, error=self.error_code != 0,
            running=bird.running, expanded_addressing=self.addressing != "normal",
            sleeping=self.sleeping, xoff=line.xoff, format=bird.fmt, stream=line.stream)

    def _flock_status(self) -> bytes:
        n = examine_reply_length(36, self.addressing)
        out = bytearray(n)
        for a, b in self.birds.items():
            if a <= n:
                out[a - 1] = flock_status_byte(
                    accessible=True, running=b.running and (self.initialised or a == 1),
                    sensor=b.sensor_index is not None, ert=b.sensor_index is None,
                    transmitters=1 if a == 1 else 0)
        return bytes(out)

    def _examine(self, bird: Bird, p: int) -> bytes | None:
        n = PARAMETERS[p].reply_length(self.addressing)
        if p in bird.params:
            return bird.params[p]
        word = lambda v: pack_words([v])  # noqa: E731
        replies = {
            0: lambda: word(self._status_word(bird)),
            1: lambda: software_revision_bytes(SOFTWARE_REVISION),
            2: lambda: bytes([CRYSTAL_MHZ, 0]),
            3: lambda: bytes([bird.scale_p3, 0]),
            4: lambda: b"\x04\x00",
            5: lambda: pack_words([0x028F] * 7),
            6: lambda: word(measurement_count_from_rate(self.rate_hz, CRYSTAL_MHZ)),
            7: lambda: word(measurement_rate_word(self.rate_hz)),
            8: lambda: b"\x00", 9: lambda: b",",
            10: lambda: self._read_error(expanded=False),
            11: lambda: b"\x00",
            12: lambda: pack_words([2, 4, 8, 32, 64, 256, 512]),
            13: lambda: pack_words([0x7333] * 7),
            14: lambda: b"\x00",
            15: lambda: (b"6DERC" if bird.sensor_index is None else b"6DFOB").ljust(10),
            16: lambda: self._read_error(expanded=True),
            17: lambda: b"\x00", 18: lambda: b"\x00",
            19: lambda: bytes([{"normal": 0, "expanded": 1, "super_expanded": 3}[self.addressing]]),
            20: lambda: bytes([60]),
            21: lambda: bytes([bird.address]),
            22: lambda: (hemisphere_bytes(bird.hemisphere) if bird.hemisphere_via_p22 else b"\x00\x00"),
            23: lambda: bytes(6), 24: lambda: bytes(6),
            25: lambda: word(1000 + bird.address), 26: lambda: word(2000 + bird.address),
            27: lambda: word(3001),
            28: lambda: bytes(10),
            29: lambda: bytes([self.report_divisor]),
            32: lambda: word(0),
            35: lambda: bytes([int(self.group)]),
            36: self._flock_status,
            50: lambda: self._auto_config_reply(n),
        }
        reply = replies.get(p)
        if reply is None:
            return None
        out = reply()
        assert len(out) == n, (p, len(out), n)
        return out

    def _read_error(self, expanded: bool) -> bytes:
        code, addr = self.error_code, self.error_address
        self.error_code, self.error_address = 0, 0  # cleared when read
        return bytes([code, addr & 0x7F]) if expanded else bytes([code])

    def _auto_config_reply(self, n: int) -> bytes:
        # byte 0: configuration mode; then a bit mask of running devices (bit a = address a)
        # and a dependents mask, each half of the rest. UNVERIFIED layout beyond its length.
        half = (n - 1) // 2
        mask = sum(1 << a for a, b in self.birds.items() if b.running and a < 8 * half)
        return bytes([0]) + mask.to_bytes(half, "little") + bytes(half)

    def _change(self, bird: Bird, p: int, data: bytes) -> None:
        if p == 35:
            self.group = data[0] == 1
        elif p == 50:
            self._auto_config(data[0])
        elif p == 7:
            self._set_rate(measurement_rate_from_word(int(unpack_words(data, signed=False)[0])))
        elif p == 6:
            self._set_rate(measurement_rate_from_count(int(unpack_words(data, signed=False)[0]),
                                                             CRYSTAL_MHZ))
        elif p == 3:
            bird.scale_p3 = 1 if data[0] == 1 else 0
        elif p == 22:
            self._set_hemisphere(bird, data, via_p22=True)
        elif p == 29:
            self._set_divisor(data[0] or 1)
        else:
            bird.params[p] = bytes(data)  # remembered so EXAMINE returns it
