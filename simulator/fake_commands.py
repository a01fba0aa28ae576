"""The fake flock's host-command state machine: bytes in, commands executed (protocol.md §2).

`CommandSet` is one part of `FakeFlock` (it runs on whichever thread feeds the flock, under the flock's
lock): it collects a command's bytes after any RS232 TO FBB prefix, routes it to its bird and carries
it out, recording errors as a real bird would (read back with EXAMINE p10/p16).
"""

from __future__ import annotations

import numpy as np

from flockcal.drivers.commands import COMMAND_DATA_BYTES, REPORT_RATE_DIVISORS, Command
from flockcal.drivers.hemispheres import HEMISPHERE_BY_BYTES
from flockcal.drivers.parameters import PARAMETERS
from flockcal.drivers.records import FORMAT_BY_COMMAND
from flockcal.simulator.fake_units import MAX_RATE_HZ, Bird, Line


class CommandSet:
    """Command parsing and execution of FakeFlock (which holds the state these methods use)."""

    def _error(self, code: int, address: int = 0) -> None:
        self.error_code, self.error_address = code, address

    def _parse(self, line: Line, byte: int) -> None:
        """One host byte through the command state machine."""
        if line.pending:
            line.pending.append(byte)
            need = self._bytes_needed(line.pending)
            if need is not None and len(line.pending) < need:
                return
            cmd = bytes(line.pending)
            line.pending.clear()
            target = line.home if line.prefix is None else line.prefix
            line.prefix = None
            if need is None:  # CHANGE/EXAMINE of an unknown parameter
                self._error(6, target)
                return
            self._execute(line, target, cmd)
            return
        if line.super_prefix:
            line.super_prefix = False
            line.prefix = byte
            return
        prefix = self._prefix_address(byte)
        if prefix is not None:
            line.prefix = prefix
            return
        if byte == 0xA0 and self.addressing == "super_expanded":
            line.super_prefix = True
            return
        if byte not in COMMAND_DATA_BYTES:
            self._error(6, line.home)
            line.prefix = None
            return
        line.pending.append(byte)
        need = self._bytes_needed(line.pending)
        if need is not None and len(line.pending) >= need:
            cmd = bytes(line.pending)
            line.pending.clear()
            target = line.home if line.prefix is None else line.prefix
            line.prefix = None
            self._execute(line, target, cmd)

    def _prefix_address(self, byte: int) -> int | None:
        if self.addressing == "super_expanded":
            return None
        if 0xF1 <= byte <= 0xFF:
            a = byte - 0xF0
            return a if self.addressing == "expanded" or a <= 14 else None
        if self.addressing == "expanded" and 0xE0 <= byte <= 0xEE:
            return byte - 0xE0 + 16
        return None

    def _bytes_needed(self, pending: bytearray) -> int | None:
        """Total length of the command being collected (None: unknown parameter)."""
        cmd = pending[0]
        if cmd in (Command.EXAMINE, Command.CHANGE):
            if len(pending) < 2:
                return 2
            p = PARAMETERS.get(pending[1])
            if p is None:
                return None
            if cmd == Command.EXAMINE:
                return 2
            return None if p.change is None else 2 + p.change
        return 1 + COMMAND_DATA_BYTES[cmd]

    def _execute(self, line: Line, target: int, cmd: bytes) -> None:
        op, data = cmd[0], cmd[1:]
        bird = self.birds.get(target)
        if bird is None:
            self._error(13, target)  # nobody answers at that FBB address
            return
        if op in FORMAT_BY_COMMAND:
            bird.fmt = FORMAT_BY_COMMAND[op]
            line.stream = False  # a format command ends a stream [§9]
        elif op == Command.POINT:
            line.stream = False
            addresses = self._set_addresses(line, target)
            if not addresses:
                self._error(9 if not self.initialised else 8, target)
                return
            # POINT returns the latest completed measurement
            k = int(np.floor((self.now - self.cycle_origin) * self.rate_hz + 1e-9))
            poses = self._cycle_poses(np.array([k]))
            self._send(line, self._records(addresses, *poses).tobytes(), self.now)
            line.records_sent += len(addresses)
        elif op == Command.STREAM:
            if not self._set_addresses(line, target):
                self._error(9 if not self.initialised else 8, target)
                return
            line.stream = True
            line.stream_address = target
        elif op == Command.STREAM_STOP:
            line.stream = False
        elif op == Command.RUN:
            self.sleeping = False
        elif op == Command.SLEEP:
            self.sleeping = True
            self.sleep_time = self.now
        elif op == Command.HEMISPHERE:
            self._set_hemisphere(bird, data, via_p22=False)
        elif op == Command.BUTTON_MODE:
            bird.button_mode = data[0] == 1
        elif op == Command.BUTTON_READ:
            self._send(line, b"\x00", self.now)
        elif op == Command.METAL:
            bird.metal = data[0] == 1
        elif op == Command.METAL_ERROR:
            self._send(line, b"\x00", self.now)
        elif op in REPORT_RATE_DIVISORS:
            self._set_divisor(REPORT_RATE_DIVISORS[op])
        elif op == Command.SYNC:
            if data[0] == 255:
                self._send(line, b"\x00\x00\x00\x00", self.now)
        elif op == Command.XOFF:
            line.xoff = True
        elif op == Command.XON:
            line.xoff = False
        elif op == Command.EXAMINE:
            reply = self._examine(bird, data[0])
            if reply is None:
                self._error(6, target)
            else:
                self._send(line, reply, self.now)
        elif op == Command.CHANGE:
            self._change(bird, data[0], data[1:])
        elif op == Command.FBB_RESET:
            for b in self.birds.values():
                b.running = b.address == 1
            self.initialised = False
        # The rest (reference frame, align, offset, boresight, next transmitter, factory test)
        # only needs its data bytes consumed.

    def _set_hemisphere(self, bird: Bird, data: bytes, via_p22: bool) -> None:
        name = HEMISPHERE_BY_BYTES.get((data[0], data[1]))
        if name is None:
            self._error(6, bird.address)
            return
        bird.hemisphere, bird.hemisphere_via_p22 = name, via_p22

    def _set_divisor(self, divisor: int) -> None:
        self._resync_cycles()
        self.report_divisor = max(1, min(127, int(divisor)))

    def _set_rate(self, rate_hz: float) -> None:
        if not 20.0 <= rate_hz <= MAX_RATE_HZ:
            self._error(31 if rate_hz > MAX_RATE_HZ else 6)
            rate_hz = float(np.clip(rate_hz, 20.0, MAX_RATE_HZ))
        self._resync_cycles()
        self.rate_hz = float(rate_hz)

    def _resync_cycles(self) -> None:
        """Re-origin the cycle grid at the last cycle (before a rate or divisor change)."""
        self.cycle_origin = self.cycle_origin + self.last_cycle / self.rate_hz
        self.last_cycle = 0
        self._cache_k = np.zeros(0, np.int64)

    def _auto_config(self, n: int) -> None:
        if not 1 <= n <= 126:
            self._error(6, 1)
            return
        if n > self.units:
            self._error(13, self.units + 1)  # the unit after the last one never answered
        self.configured_units = min(n, self.units)
        for b in self.birds.values():
            b.running = b.address <= self.configured_units
        self.initialised = True
