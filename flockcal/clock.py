"""Clocks handed to the parts that measure time: `monotonic()` for durations, deadlines and ages (never
stepped), `wall()` only for stamps shown to people. `SystemClock` is the machine's; `ManualClock` is one a
test moves by hand, stepping the wall clock the way NTP does.
"""

from __future__ import annotations

import errno
import os
import threading
import time
from typing import Protocol

__all__ = ["Clock", "ManualClock", "SystemClock", "SYSTEM"]


class Clock(Protocol):
    """Where a part reads the time. `monotonic()`: seconds on a clock that is never stepped (its origin is
    arbitrary); `wall()`: unix seconds, which an operator or NTP may step either way; `epoch()`: an id of the
    monotonic clock's origin (readings under one id compare across processes; None: not known)."""

    def monotonic(self) -> float: ...

    def wall(self) -> float: ...

    def epoch(self) -> str | None: ...

    def sleep(self, seconds: float) -> None: ...


class SystemClock:
    """The machine's clocks. `monotonic()` is the kernel's boot clock as /proc/uptime gives it (10 ms steps):
    it counts time suspended (a night in standby ages a recording; it is no step of the wall clock) and no
    one can step it. It is read from the kernel's file, not through the C library: tools that fake the time
    for a program (libfaketime) move every clock the library reports, so a faked step of the wall clock
    would move it too. Where /proc/uptime cannot be read, `time.monotonic()`."""

    def __init__(self, uptime: str = "/proc/uptime", boot_id: str = "/proc/sys/kernel/random/boot_id"):
        self._boot_id = _read(boot_id)
        try:
            self._fd: int | None = os.open(uptime, os.O_RDONLY | os.O_CLOEXEC)
            self._uptime()
        except (OSError, ValueError, IndexError):
            self._fd = None

    def _uptime(self) -> float:
        # pread at 0 makes the kernel write the figure afresh (1.5 µs; no open and close per reading).
        return float(os.pread(self._fd, 64, 0).split()[0])

    def monotonic(self) -> float:
        if self._fd is None:
            return time.monotonic()
        return self._uptime()

    def wall(self) -> float:
        return time.time()

    def epoch(self) -> str | None:
        """The boot id: boot-clock readings taken in one boot compare across restarts of the service."""
        return self._boot_id if self._fd is not None else None

    def sleep(self, seconds: float) -> None:
        """Wait `seconds`: time.sleep, or a timed wait where the C library refuses it (EINVAL: CPython's
        absolute clock_nanosleep under libfaketime with its monotonic clocks left real, as the clock tests run)."""
        if seconds <= 0:
            return
        try:
            time.sleep(seconds)
        except OSError as exc:
            if exc.errno != errno.EINVAL:
                raise
            threading.Event().wait(seconds)


def _read(path: str) -> str | None:
    try:
        with open(path) as fh:
            return fh.read().strip() or None
    except OSError:
        return None


class ManualClock:
    """A clock a test moves: `advance(s)` moves both clocks as time passing does, `step_wall(s)` moves the
    wall clock alone (an NTP step: forward when s > 0, back when s < 0). Thread-safe."""

    def __init__(self, wall: float = 1.7e9, monotonic: float = 1000.0, epoch: str | None = "manual"):
        self._lock = threading.Lock()
        self._wall = float(wall)
        self._mono = float(monotonic)
        self._epoch = epoch

    def monotonic(self) -> float:
        with self._lock:
            return self._mono

    def wall(self) -> float:
        with self._lock:
            return self._wall

    def epoch(self) -> str | None:
        return self._epoch

    def advance(self, seconds: float) -> None:
        if seconds < 0:
            raise ValueError("time passing cannot go back; step_wall steps the wall clock")
        with self._lock:
            self._mono += seconds
            self._wall += seconds

    def step_wall(self, seconds: float) -> None:
        with self._lock:
            self._wall += seconds

    def sleep(self, seconds: float) -> None:
        """Time passes at once: nothing waits on a manual clock."""
        self.advance(max(seconds, 0.0))


SYSTEM = SystemClock()
