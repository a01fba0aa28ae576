"""A fake Flock of Birds: the RS-232 protocol as a byte-driven state machine, with a line model.

`FakeFlock` takes host bytes, answers commands and streams records of a pose source at the
measurement rate, limited by each port's baud rate (8N1: baud/10 bytes/s). Transports (a pty, the
sim:// URL handler) only move bytes; time comes from a clock you pass (wall or manual).
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from typing import Callable, Protocol

import numpy as np

from flockcal.drivers import codec
from flockcal.rotations import from_euler
from flockcal.drivers.codec import Command
from flockcal.errors import FlockcalError


class FakeTrackerError(FlockcalError, ValueError):
    """Bad fake-tracker set-up (too many birds, a port that does not exist)."""


class PoseSource(Protocol):
    """What the fake flock measures: world = transmitter frame (+Z down), metres."""

    names: tuple[str, ...]
    n_sensors: int

    def poses(self, times: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """times (n,) → rotations (n,m,3,3) sensor→transmitter, positions (n,m,3), valid (n,m)."""


class ManualClock:
    """A clock tests drive by hand: `advance(dt)` moves simulated time on."""

    def __init__(self, t: float = 0.0) -> None:
        self.t = float(t)

    def __call__(self) -> float:
        return self.t

    def advance(self, dt: float) -> float:
        self.t += float(dt)
        return self.t


class WallClock:
    """Seconds of wall time since construction (monotonic)."""

    def __init__(self) -> None:
        self._t0 = time.monotonic()

    def __call__(self) -> float:
        return time.monotonic() - self._t0


SOFTWARE_REVISION = 3.67
CRYSTAL_MHZ = 25
DEFAULT_RATE_HZ = 103.0  # p7 default 0x6700
MAX_RATE_HZ = 180.0  # the bird cannot measure faster [MAN p146]
OUTPUT_BUFFER_LIMIT = 65536  # bytes delivered but not read before the oldest are lost (host overrun)


@dataclass
class _Bird:
    """Per-address state (one unit on the FBB)."""

    address: int
    sensor_index: int | None  # index into the pose source; None for an ERC/ERT unit
    fmt: codec.RecordFormat = codec.DEFAULT_FORMAT
    hemisphere: str = "forward"
    hemisphere_via_p22: bool = False
    button_mode: bool = False
    metal: bool = False
    running: bool = False
    scale_p3: int = 0  # position scaling (p3 byte 0): 0 = 36 in, 1 = 72 in; each bird keeps its own
    params: dict[int, bytes] = field(default_factory=dict)


@dataclass
class _Line:
    """One RS-232 port: the parser of host bytes and the bird→host byte queue with delivery times."""

    index: int
    home: int  # address a command without an RS232-TO-FBB prefix goes to
    baud: float
    data: bytearray = field(default_factory=bytearray)
    done: np.ndarray = field(default_factory=lambda: np.zeros(0))  # delivery time of each byte
    free_at: float = 0.0  # when the transmitter of this line is idle again
    connected: bool = True
    stream: bool = False
    stream_address: int | None = None  # non-group STREAM target
    xoff: bool = False
    stalled_until: float = -np.inf
    drop_pending: int = 0
    # parser
    pending: bytearray = field(default_factory=bytearray)
    prefix: int | None = None
    super_prefix: bool = False
    # counters
    records_sent: int = 0
    sets_skipped: int = 0
    bytes_lost: int = 0
    bytes_received: int = 0

    @property
    def bytes_per_second(self) -> float:
        return self.baud / 10.0



class LineFaults:
    """Line faults of the `flock` an object owns (a pty server, a sim:// simulation), forwarded so that
    callers need only that object; `port=None` means every port."""

    flock: "FakeFlock"

    def inject_garbage(self, nbytes: int, port: int | None = None) -> None:
        self.flock.inject_garbage(nbytes, port)

    def drop_bytes(self, n: int, port: int | None = None) -> None:
        self.flock.drop_bytes(n, port)

    def stall(self, seconds: float, port: int | None = None) -> None:
        self.flock.stall(seconds, port)

    def set_error(self, code: int, address: int = 0) -> None:
        self.flock.set_error(code, address)


class FakeFlock:
    """A flock of birds on one or more RS-232 ports, answering the FOB command set.

    source: a PoseSource. birds: sensor birds (default: all of the source's sensors), at FBB
    addresses 1..birds, or 2..birds+1 after an ERC/ERT at address 1 when `ert`. ports: 1 (one
    line to the master) or `birds` (one line per sensor bird, sharing the flock's clock).
    clock: a callable giving seconds (`ManualClock` for tests, `WallClock` for real time).
    scale_inches: power-up position scale, 36 or 72 (p3); default the source's `full_scale_in`
    or 36. With `ert` the scale is 144 in, as on the real extended-range transmitter.
    pose_lookahead: seconds of measurement cycles asked of the source in one call (sources with
    a large per-call cost keep up; a fault injected into the source shows after the block).
    """

    def __init__(self, source: PoseSource, *, birds: int | None = None, ert: bool = False,
                 rate_hz: float = DEFAULT_RATE_HZ, baud: float = 115200, ports: int = 1,
                 clock: Callable[[], float] | None = None, scale_inches: float | None = None,
                 quaternion_convention: str = "fob", seed: int = 0,
                 buffer_limit: int = OUTPUT_BUFFER_LIMIT, pose_lookahead: float = 0.1) -> None:
        n = source.n_sensors if birds is None else int(birds)
        if not 1 <= n <= source.n_sensors:
            raise FakeTrackerError(f"birds must be 1..{source.n_sensors} (sensors of the pose source), not {n}")
        units = n + int(ert)
        if units > 126:
            raise FakeTrackerError(f"a flock holds at most 126 units, not {units}")
        if ports not in (1, n):
            raise FakeTrackerError(f"ports must be 1 (one line to the master) or {n} (one per bird), not {ports}")
        self.source = source
        self.clock = clock if clock is not None else WallClock()
        self.ert = bool(ert)
        self.n_birds = n
        self.units = units
        self.addressing = ("normal" if units <= 14 else "expanded" if units <= 30 else "super_expanded")
        self.quaternion_convention = quaternion_convention
        self.buffer_limit = int(buffer_limit)
        self.pose_lookahead = float(pose_lookahead)
        self._cache_k = np.zeros(0, np.int64)
        self._cache = None
        self._lock = threading.RLock()
        self._rng = np.random.default_rng(seed)
        # The source may say which scale its motion needs (a walking performer needs 72 in).
        if scale_inches is None:
            scale_inches = float(getattr(source, "full_scale_in", 36.0))
        self._power_up_scale = 72.0 if scale_inches == 72.0 else 36.0
        self._power_up_rate = float(rate_hz)
        first = 1 + int(ert)
        self.birds: dict[int, _Bird] = {}
        if ert:
            self.birds[1] = _Bird(1, None)
        for i in range(n):
            self.birds[first + i] = _Bird(first + i, i)
        self.sensor_addresses = list(range(first, first + n))
        homes = [1] if ports == 1 else self.sensor_addresses
        self.lines = [_Line(k, home, float(baud)) for k, home in enumerate(homes)]
        self.now = float(self.clock())
        self.error_code = 0
        self.error_address = 0
        self.standby = False
        self._power_up()

    # ------------------------------------------------------------------ state

    def _power_up(self) -> None:
        """State after power-up or an RTS reset [MAN p38]."""
        self.group = False
        self.sleeping = False
        self.sleep_time = self.now
        self.report_divisor = 1
        self.rate_hz = min(self._power_up_rate, MAX_RATE_HZ)
        self.initialised = False
        self.configured_units = 0
        self.cycle_origin = self.now
        self.last_cycle = 0
        self._cache_k = np.zeros(0, np.int64)
        for b in self.birds.values():
            b.fmt, b.hemisphere, b.hemisphere_via_p22 = codec.DEFAULT_FORMAT, "forward", False
            b.button_mode = b.metal = False
            b.scale_p3 = 1 if self._power_up_scale == 72.0 else 0
            b.params = {}
            # The master (and only it) runs before AUTO-CONFIG.
            b.running = b.address == 1
        for line in self.lines:
            line.stream, line.stream_address, line.xoff = False, None, False
            line.pending.clear()
            line.prefix, line.super_prefix = None, False

    def bird_scale_inches(self, bird: _Bird) -> float:
        """Position full scale of one bird's records (every bird has its own p3; an ERT fixes 144 in)."""
        return 144.0 if self.ert else (72.0 if bird.scale_p3 else 36.0)

    @property
    def scale_inches(self) -> float:
        """The first sensor bird's position full scale (all of them, once a driver has set them alike)."""
        return self.bird_scale_inches(self.birds[self.sensor_addresses[0]])

    @property
    def n_ports(self) -> int:
        return len(self.lines)

    def set_standby(self, on: bool) -> None:
        """RTS high (or the front switch on STANDBY): silent and deaf; leaving it is a power-up."""
        with self._lock:
            self._sync()
            if self.standby and not on:
                self._power_up()
            self.standby = bool(on)
            if on:
                for line in self.lines:
                    line.stream = False

    def power_up_reset(self) -> None:
        """What toggling RTS (or FLY/STANDBY) does: everything back to power-up defaults."""
        with self._lock:
            self._sync()
            self._power_up()

    # ------------------------------------------------------------------ transport API

    def write(self, data: bytes, port: int = 0) -> int:
        """Host → bird bytes on `port`; answers are queued on the same port."""
        with self._lock:
            self._sync()
            line = self._line(port)
            if not line.connected or self.standby:
                return len(data)
            line.bytes_received += len(data)
            for byte in bytes(data):
                self._parse(line, byte)
            return len(data)

    def read(self, port: int = 0, size: int | None = None) -> bytes:
        """Bird → host bytes that have arrived on `port` by now (at most `size`)."""
        with self._lock:
            self._sync()
            line = self._line(port)
            k = self._arrived(line)
            if size is not None:
                k = min(k, int(size))
            out = bytes(line.data[:k])
            del line.data[:k]
            line.done = line.done[k:]
            return out

    def in_waiting(self, port: int = 0) -> int:
        with self._lock:
            self._sync()
            return self._arrived(self._line(port))

    def next_arrival(self, port: int = 0) -> float | None:
        """Clock time at which the next not-yet-arrived byte will arrive (None: nothing queued)."""
        with self._lock:
            line = self._line(port)
            k = self._arrived(line)
            return float(line.done[k]) if k < len(line.done) else None

    def discard_input(self, port: int = 0) -> None:
        """The host flushed its input queue: bytes already arrived are gone."""
        with self._lock:
            self._sync()
            line = self._line(port)
            k = self._arrived(line)
            del line.data[:k]
            line.done = line.done[k:]

    def set_baud(self, baud: float, port: int | None = None) -> None:
        """Throughput of a line (8N1: baud/10 bytes per second)."""
        with self._lock:
            self._sync()
            for line in self._lines(port):
                line.baud = float(baud)

    def advance(self) -> None:
        """Bring the flock up to the clock's time (transports call this; read/write do it too)."""
        with self._lock:
            self._sync()

    # ------------------------------------------------------------------ fault injection

    def inject_garbage(self, nbytes: int, port: int | None = None) -> None:
        """Queue `nbytes` random bytes with bit 7 clear (they cannot start a record)."""
        with self._lock:
            self._sync()
            for line in self._lines(port):
                self._send(line, self._rng.integers(0, 0x80, nbytes, dtype=np.uint8).tobytes(), self.now)

    def drop_bytes(self, n: int, port: int | None = None) -> None:
        """Lose the next `n` bytes of the outgoing stream (those not yet on the wire)."""
        with self._lock:
            self._sync()
            for line in self._lines(port):
                line.drop_pending += int(n)
                self._apply_drop(line)

    def stall(self, seconds: float, port: int | None = None) -> None:
        """The bird sends nothing for `seconds` (records due meanwhile are lost), then resumes."""
        with self._lock:
            self._sync()
            for line in self._lines(port):
                line.stalled_until = self.now + float(seconds)
                line.free_at = max(line.free_at, line.stalled_until)

    def disconnect(self, port: int | None = None) -> None:
        """Cut the cable: the bird keeps running but nothing crosses the line."""
        with self._lock:
            self._sync()
            for line in self._lines(port):
                line.connected = False
                line.data.clear()
                line.done = np.zeros(0)
                line.pending.clear()
                line.prefix, line.super_prefix = None, False

    def reconnect(self, port: int | None = None) -> None:
        """Plug the cable back in; the bird's state (stream, formats) is as it was."""
        with self._lock:
            self._sync()
            for line in self._lines(port):
                line.connected = True
                line.free_at = max(line.free_at, self.now)

    def set_error(self, code: int, address: int = 0) -> None:
        """Put `code` in the error register (p10/p16), as if the bird had detected it."""
        with self._lock:
            self.error_code = int(code) & 0xFF
            self.error_address = int(address)

    def connected(self, port: int = 0) -> bool:
        return self._line(port).connected

    def streaming(self, port: int = 0) -> bool:
        return self._line(port).stream

    def stats(self, port: int = 0) -> dict:
        line = self._line(port)
        return {"records_sent": line.records_sent, "sets_skipped": line.sets_skipped,
                "bytes_lost": line.bytes_lost, "bytes_received": line.bytes_received,
                "baud": line.baud, "queued": len(line.data)}

    # ------------------------------------------------------------------ internals: lines

    def _line(self, port: int) -> _Line:
        if not 0 <= port < len(self.lines):
            raise FakeTrackerError(f"port {port} does not exist; this flock has {len(self.lines)} port(s)")
        return self.lines[port]

    def _lines(self, port: int | None) -> list[_Line]:
        return list(self.lines) if port is None else [self._line(port)]

    def _arrived(self, line: _Line) -> int:
        return int(np.searchsorted(line.done, self.now, side="right"))

    def _send(self, line: _Line, data: bytes, t: float) -> None:
        """Put bytes on the wire at time t (after anything already being sent)."""
        if not data or not line.connected:
            return
        start = max(t, line.free_at)
        bps = line.bytes_per_second
        line.data += data
        line.done = np.concatenate([line.done, start + np.arange(1, len(data) + 1) / bps])
        line.free_at = start + len(data) / bps
        if line.drop_pending:
            self._apply_drop(line)

    def _apply_drop(self, line: _Line) -> None:
        k = self._arrived(line)
        n = min(line.drop_pending, len(line.data) - k)
        if n > 0:
            del line.data[k:k + n]
            line.done = np.delete(line.done, np.s_[k:k + n])
            line.drop_pending -= n

    def _sync(self) -> None:
        """Advance to the clock: stream the measurement cycles that have passed, per line."""
        t = float(self.clock())
        if t < self.now:
            return
        k1 = int(np.floor((t - self.cycle_origin) * self.rate_hz + 1e-9))
        if k1 > self.last_cycle:
            cycles = np.arange(self.last_cycle + 1, k1 + 1)
            cycles = cycles[cycles % self.report_divisor == 0]
            streaming = [ln for ln in self.lines if ln.stream]
            if len(cycles) and streaming:
                poses = self._cycle_poses(cycles)
                times = self.cycle_origin + cycles / self.rate_hz
                for line in streaming:
                    self._stream(line, times, poses)
            self.last_cycle = k1
        self.now = t
        for line in self.lines:
            self._cap(line)

    def _cycle_poses(self, cycles: np.ndarray):
        """Source poses at measurement cycles, asked for in blocks of `pose_lookahead` seconds."""
        if self.sleeping:  # transmitter off: the data stop changing
            rot, pos, valid = self.source.poses(np.array([self.sleep_time]))
            n = len(cycles)
            return (np.repeat(rot, n, 0), np.repeat(pos, n, 0), np.repeat(np.asarray(valid, bool), n, 0))
        ck = self._cache_k
        if not (len(ck) and ck[0] <= cycles[0] and cycles[-1] <= ck[-1]):
            last = max(int(cycles[-1]), int(cycles[0] + np.ceil(self.pose_lookahead * self.rate_hz)))
            ck = np.arange(int(cycles[0]), last + 1)
            rot, pos, valid = self.source.poses(self.cycle_origin + ck / self.rate_hz)
            self._cache_k = ck
            self._cache = (np.asarray(rot), np.asarray(pos), np.asarray(valid, bool))
        i = cycles - ck[0]
        rot, pos, valid = self._cache
        return rot[i], pos[i], valid[i]

    def _cap(self, line: _Line) -> None:
        # A host that does not read loses the oldest bytes, like an overrun OS buffer.
        k = self._arrived(line)
        excess = k - self.buffer_limit
        if excess > 0:
            del line.data[:excess]
            line.done = line.done[excess:]
            line.bytes_lost += excess

    def _stream(self, line: _Line, times: np.ndarray, poses) -> None:
        """Records for cycle times (each ≥ the last cycle), skipping sets the line cannot carry."""
        addresses = self._set_addresses(line, line.stream_address)
        if not addresses or line.xoff or not line.connected:
            line.sets_skipped += len(times)
            return
        size = sum(self._record_length(self.birds[a]) for a in addresses)
        duration = size / line.bytes_per_second
        period = self.report_divisor / self.rate_hz
        # The bird starts a set only when the previous one has left its UART (no backlog), so
        # a set longer than the report period makes it skip whole cycles.
        stride = max(1, int(np.ceil(duration / period - 1e-9)))
        ok = times >= max(line.free_at, line.stalled_until) - 1e-12
        if not np.any(ok):
            line.sets_skipped += len(times)
            return
        first = int(np.argmax(ok))
        sel = np.arange(first, len(times), stride)
        line.sets_skipped += len(times) - len(sel)
        t_sel = times[sel]
        data = self._records(addresses, *(a[sel] for a in poses))  # (k, size)
        bps = line.bytes_per_second
        line.data += data.tobytes()
        line.done = np.concatenate([line.done, (t_sel[:, None] + np.arange(1, size + 1) / bps).ravel()])
        line.free_at = float(t_sel[-1] + duration)
        line.records_sent += len(t_sel) * len(addresses)
        if line.drop_pending:
            self._apply_drop(line)

    def _set_addresses(self, line: _Line, target: int | None) -> list[int]:
        """Birds whose records make up one POINT/STREAM reply on this line."""
        if self.group and len(self.lines) == 1:
            return [a for a in self.sensor_addresses if self.birds[a].running]
        a = line.home if target is None else target
        bird = self.birds.get(a)
        return [a] if bird is not None and bird.running and bird.sensor_index is not None else []

    def _record_length(self, bird: _Bird) -> int:
        return codec.record_length(bird.fmt, group=self.group, button=bird.button_mode, metal=bird.metal)

    def _records(self, addresses: list[int], rot, pos, valid) -> np.ndarray:
        """(k, set bytes) uint8: one record per address for each of k measurements, in address order."""
        n = len(rot)
        parts = []
        for a in addresses:
            bird = self.birds[a]
            i = bird.sensor_index
            p = codec.fold_to_hemisphere(pos[:, i], bird.hemisphere)
            words = codec.data_words(bird.fmt, rot[:, i], p, scale_inches=self.bird_scale_inches(bird),
                                     quaternion_convention=self.quaternion_convention)
            words[~valid[:, i]] = 0  # a saturated/absent sensor sends all-zero data
            rec = codec.encode_words(words)
            extra = []
            if bird.button_mode:
                extra.append(np.zeros(n, np.uint8))
            if bird.metal:
                extra.append(np.zeros(n, np.uint8))
            if self.group:
                extra.append(np.full(n, a & 0x7F, np.uint8))
            parts.append(np.concatenate([rec, np.stack(extra, 1)], 1) if extra else rec)
        return np.concatenate(parts, axis=1)

    # ------------------------------------------------------------------ internals: commands

    def _error(self, code: int, address: int = 0) -> None:
        self.error_code, self.error_address = code, address

    def _parse(self, line: _Line, byte: int) -> None:
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
        if byte not in codec.COMMAND_DATA_BYTES:
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
            p = codec.PARAMETERS.get(pending[1])
            if p is None:
                return None
            if cmd == Command.EXAMINE:
                return 2
            return None if p.change is None else 2 + p.change
        return 1 + codec.COMMAND_DATA_BYTES[cmd]

    def _execute(self, line: _Line, target: int, cmd: bytes) -> None:
        op, data = cmd[0], cmd[1:]
        bird = self.birds.get(target)
        if bird is None:
            self._error(13, target)  # nobody answers at that FBB address
            return
        if op in codec.FORMAT_BY_COMMAND:
            bird.fmt = codec.FORMAT_BY_COMMAND[op]
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
        elif op in codec.REPORT_RATE_DIVISORS:
            self._set_divisor(codec.REPORT_RATE_DIVISORS[op])
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

    def _set_hemisphere(self, bird: _Bird, data: bytes, via_p22: bool) -> None:
        name = codec.HEMISPHERE_BY_BYTES.get((data[0], data[1]))
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

    def _status_word(self, bird: _Bird) -> int:
        line = next((ln for ln in self.lines if ln.home == bird.address), self.lines[0])
        return codec.encode_status_word(
            master=bird.address == 1, initialised=self.initialised, error=self.error_code != 0,
            running=bird.running, expanded_addressing=self.addressing != "normal",
            sleeping=self.sleeping, xoff=line.xoff, format=bird.fmt, stream=line.stream)

    def _flock_status(self) -> bytes:
        n = codec.examine_reply_length(36, self.addressing)
        out = bytearray(n)
        for a, b in self.birds.items():
            if a <= n:
                out[a - 1] = codec.flock_status_byte(
                    accessible=True, running=b.running and (self.initialised or a == 1),
                    sensor=b.sensor_index is not None, ert=b.sensor_index is None,
                    transmitters=1 if a == 1 else 0)
        return bytes(out)

    def _examine(self, bird: _Bird, p: int) -> bytes | None:
        n = codec.PARAMETERS[p].reply_length(self.addressing)
        if p in bird.params:
            return bird.params[p]
        word = lambda v: codec.pack_words([v])  # noqa: E731
        replies = {
            0: lambda: word(self._status_word(bird)),
            1: lambda: codec.software_revision_bytes(SOFTWARE_REVISION),
            2: lambda: bytes([CRYSTAL_MHZ, 0]),
            3: lambda: bytes([bird.scale_p3, 0]),
            4: lambda: b"\x04\x00",
            5: lambda: codec.pack_words([0x028F] * 7),
            6: lambda: word(codec.measurement_count_from_rate(self.rate_hz, CRYSTAL_MHZ)),
            7: lambda: word(codec.measurement_rate_word(self.rate_hz)),
            8: lambda: b"\x00", 9: lambda: b",",
            10: lambda: self._read_error(expanded=False),
            11: lambda: b"\x00",
            12: lambda: codec.pack_words([2, 4, 8, 32, 64, 256, 512]),
            13: lambda: codec.pack_words([0x7333] * 7),
            14: lambda: b"\x00",
            15: lambda: (b"6DERC" if bird.sensor_index is None else b"6DFOB").ljust(10),
            16: lambda: self._read_error(expanded=True),
            17: lambda: b"\x00", 18: lambda: b"\x00",
            19: lambda: bytes([{"normal": 0, "expanded": 1, "super_expanded": 3}[self.addressing]]),
            20: lambda: bytes([60]),
            21: lambda: bytes([bird.address]),
            22: lambda: (codec.hemisphere_bytes(bird.hemisphere) if bird.hemisphere_via_p22 else b"\x00\x00"),
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

    def _change(self, bird: _Bird, p: int, data: bytes) -> None:
        if p == 35:
            self.group = data[0] == 1
        elif p == 50:
            self._auto_config(data[0])
        elif p == 7:
            self._set_rate(codec.measurement_rate_from_word(int(codec.unpack_words(data, signed=False)[0])))
        elif p == 6:
            self._set_rate(codec.measurement_rate_from_count(int(codec.unpack_words(data, signed=False)[0]),
                                                             CRYSTAL_MHZ))
        elif p == 3:
            bird.scale_p3 = 1 if data[0] == 1 else 0
        elif p == 22:
            self._set_hemisphere(bird, data, via_p22=True)
        elif p == 29:
            self._set_divisor(data[0] or 1)
        else:
            bird.params[p] = bytes(data)  # remembered so EXAMINE returns it


class SmoothSource:
    """A small deterministic pose source: m sensors on slow independent orbits inside 0.8 m."""

    def __init__(self, n_sensors: int = 4, seed: int = 0, radius: float = 0.5) -> None:
        rng = np.random.default_rng(seed)
        self.n_sensors = n_sensors
        self.names = tuple(f"s{i}" for i in range(n_sensors))
        self._centre = rng.uniform(-0.2, 0.2, (n_sensors, 3)) + [0.3, 0.0, 0.0]
        self._amp = rng.uniform(0.05, radius - 0.2, (n_sensors, 3))
        self._freq = rng.uniform(0.2, 1.0, (n_sensors, 3))
        self._phase = rng.uniform(0, 2 * np.pi, (n_sensors, 3))
        self._wfreq = rng.uniform(0.1, 0.8, (n_sensors, 3))
        self._valid_until = np.full(n_sensors, np.inf)

    def poses(self, times: np.ndarray):
        t = np.asarray(times, dtype=float)[:, None, None]
        pos = self._centre + self._amp * np.sin(2 * np.pi * self._freq * t + self._phase)
        ang = 3.0 * np.sin(2 * np.pi * self._wfreq * t + self._phase)  # sweeps every Euler range
        rot = from_euler(ang[..., 0], ang[..., 1] / 2.0, ang[..., 2])
        valid = np.broadcast_to(t[:, :, 0] < self._valid_until, pos.shape[:2]).copy()
        return rot, pos, valid

    def invalidate(self, sensor: int, after: float = -np.inf) -> None:
        """Sensor `sensor` gives no valid data from time `after` on (tests of the zero record)."""
        self._valid_until[sensor] = after
