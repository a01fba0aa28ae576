"""A fake Flock of Birds: the RS-232 protocol as a byte-driven state machine, with a line model.

`FakeFlock` takes host bytes, answers commands (fake_commands, fake_parameters) and streams records of
a pose source at the measurement rate, limited by each port's baud rate (8N1: baud/10 bytes/s).
Transports (a pty, the sim:// URL handler) only move bytes; time comes from a `flockcal.clock.Clock` (the
machine's, or a test's `ManualClock`).
"""

from __future__ import annotations

import threading
from typing import Protocol

import numpy as np
# Quaternion records are encoded on the streaming thread, through scipy's Rotation, which flockcal.rotations
# imports on first use (for the CLI's start-up): imported here, so a fake tracker's first quaternion cycles
# do not wait ~0.2 s for it (they were lost, and the rest came in a burst).
import scipy.spatial.transform  # noqa: F401

from flockcal.clock import SYSTEM, Clock
from flockcal.drivers.hemispheres import fold_to_hemisphere
from flockcal.drivers.records import DEFAULT_FORMAT, data_words, record_length
from flockcal.drivers.words import encode_words
from flockcal.errors import FlockcalError
from flockcal.simulator.fake_commands import CommandSet
from flockcal.simulator.fake_parameters import ParameterSet
from flockcal.simulator.fake_units import DEFAULT_RATE_HZ, MAX_RATE_HZ, OUTPUT_BUFFER_LIMIT, Bird, Line


class FakeTrackerError(FlockcalError, ValueError):
    """Bad fake-tracker set-up (too many birds, a port that does not exist)."""


class PoseSource(Protocol):
    """What the fake flock measures: world = transmitter frame (+Z down), metres."""

    names: tuple[str, ...]
    n_sensors: int

    def poses(self, times: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """times (n,) → rotations (n,m,3,3) sensor→transmitter, positions (n,m,3), valid (n,m)."""









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


class FakeFlock(CommandSet, ParameterSet):
    """A flock of birds on one or more RS-232 ports, answering the FOB command set.

    source: a PoseSource. birds: sensor birds (default: all of the source's sensors), at FBB
    addresses 1..birds, or 2..birds+1 after an ERC/ERT at address 1 when `ert`. ports: 1 (one
    line to the master) or `birds` (one line per sensor bird, sharing the flock's clock).
    clock: the `flockcal.clock.Clock` it runs on (the machine's; a test's `ManualClock`); the flock's time
    (`time()`) is its monotonic seconds since the flock was made.
    scale_inches: power-up position scale, 36 or 72 (p3); default the source's `full_scale_in`
    or 36. With `ert` the scale is 144 in, as on the real extended-range transmitter.
    pose_lookahead: seconds of measurement cycles asked of the source in one call (sources with
    a large per-call cost keep up; a fault injected into the source shows after the block).
    """

    def __init__(self, source: PoseSource, *, birds: int | None = None, ert: bool = False,
                 rate_hz: float = DEFAULT_RATE_HZ, baud: float = 115200, ports: int = 1,
                 clock: Clock = SYSTEM, scale_inches: float | None = None,
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
        self.clock = clock
        self.origin = clock.monotonic()  # the flock's time 0 on its clock
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
        self.birds: dict[int, Bird] = {}
        if ert:
            self.birds[1] = Bird(1, None)
        for i in range(n):
            self.birds[first + i] = Bird(first + i, i)
        self.sensor_addresses = list(range(first, first + n))
        homes = [1] if ports == 1 else self.sensor_addresses
        self.lines = [Line(k, home, float(baud)) for k, home in enumerate(homes)]
        self.now = self.time()
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
            b.fmt, b.hemisphere, b.hemisphere_via_p22 = DEFAULT_FORMAT, "forward", False
            b.button_mode = b.metal = False
            b.scale_p3 = 1 if self._power_up_scale == 72.0 else 0
            b.params = {}
            # The master (and only it) runs before AUTO-CONFIG.
            b.running = b.address == 1
        for line in self.lines:
            line.stream, line.stream_address, line.xoff = False, None, False
            line.pending.clear()
            line.prefix, line.super_prefix = None, False

    def bird_scale_inches(self, bird: Bird) -> float:
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

    def time(self) -> float:
        """The flock's time: seconds on its clock since it was made."""
        return self.clock.monotonic() - self.origin

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

    def _line(self, port: int) -> Line:
        if not 0 <= port < len(self.lines):
            raise FakeTrackerError(f"port {port} does not exist; this flock has {len(self.lines)} port(s)")
        return self.lines[port]

    def _lines(self, port: int | None) -> list[Line]:
        return list(self.lines) if port is None else [self._line(port)]

    def _arrived(self, line: Line) -> int:
        return int(np.searchsorted(line.done, self.now, side="right"))

    def _send(self, line: Line, data: bytes, t: float) -> None:
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

    def _apply_drop(self, line: Line) -> None:
        k = self._arrived(line)
        n = min(line.drop_pending, len(line.data) - k)
        if n > 0:
            del line.data[k:k + n]
            line.done = np.delete(line.done, np.s_[k:k + n])
            line.drop_pending -= n

    def _sync(self) -> None:
        """Advance to the clock: stream the measurement cycles that have passed, per line."""
        t = self.time()
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

    def _cap(self, line: Line) -> None:
        # A host that does not read loses the oldest bytes, like an overrun OS buffer.
        k = self._arrived(line)
        excess = k - self.buffer_limit
        if excess > 0:
            del line.data[:excess]
            line.done = line.done[excess:]
            line.bytes_lost += excess

    def _stream(self, line: Line, times: np.ndarray, poses) -> None:
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

    def _set_addresses(self, line: Line, target: int | None) -> list[int]:
        """Birds whose records make up one POINT/STREAM reply on this line."""
        if self.group and len(self.lines) == 1:
            return [a for a in self.sensor_addresses if self.birds[a].running]
        a = line.home if target is None else target
        bird = self.birds.get(a)
        return [a] if bird is not None and bird.running and bird.sensor_index is not None else []

    def _record_length(self, bird: Bird) -> int:
        return record_length(bird.fmt, group=self.group, button=bird.button_mode, metal=bird.metal)

    def _records(self, addresses: list[int], rot, pos, valid) -> np.ndarray:
        """(k, set bytes) uint8: one record per address for each of k measurements, in address order."""
        n = len(rot)
        parts = []
        for a in addresses:
            bird = self.birds[a]
            i = bird.sensor_index
            p = fold_to_hemisphere(pos[:, i], bird.hemisphere)
            words = data_words(bird.fmt, rot[:, i], p, scale_inches=self.bird_scale_inches(bird),
                                     quaternion_convention=self.quaternion_convention)
            words[~valid[:, i]] = 0  # a saturated/absent sensor sends all-zero data
            rec = encode_words(words)
            extra = []
            if bird.button_mode:
                extra.append(np.zeros(n, np.uint8))
            if bird.metal:
                extra.append(np.zeros(n, np.uint8))
            if self.group:
                extra.append(np.full(n, a & 0x7F, np.uint8))
            parts.append(np.concatenate([rec, np.stack(extra, 1)], 1) if extra else rec)
        return np.concatenate(parts, axis=1)




