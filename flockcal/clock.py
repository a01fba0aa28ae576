"""Clocks handed to the parts that measure time: `monotonic()` for durations, deadlines, timeouts and cadences
(never stepped), `wall()` only for stamps shown to people, `sleep`/`wait` for waits measured on the same clock.
`SystemClock` is the machine's; `ManualClock` is one a test moves by hand (the fake tracker, the driver and the
service all read it), stepping the wall clock the way NTP does.
"""

from __future__ import annotations

import errno
import functools
import os
import threading
import time
from typing import Protocol

__all__ = ["Clock", "ManualClock", "SystemClock", "SYSTEM", "Waitable"]


class Waitable(Protocol):
    """What a clock can wait on: a `threading.Event`, or a `threading.Condition` its caller holds."""

    def wait(self, timeout: float | None = None) -> bool: ...


class Clock(Protocol):
    """Where a part reads the time. `monotonic()`: seconds on a clock that is never stepped (its origin is
    arbitrary); `wall()`: unix seconds, which an operator or NTP may step either way; `epoch()`: an id of the
    monotonic clock's origin (readings under one id compare across processes; None: not known).
    `sleep(s)` waits `s` seconds of this clock; `wait(w, timeout)` waits on `w` (an Event, or a Condition held)
    for at most `timeout` seconds of this clock, and says whether it was set or notified (a Condition's waiter
    looks again at what it waits for, as after any notify: a clock may wake it early)."""

    def monotonic(self) -> float: ...

    def wall(self) -> float: ...

    def epoch(self) -> str | None: ...

    def sleep(self, seconds: float) -> None: ...

    def wait(self, waitable: Waitable, timeout: float | None) -> bool: ...


class SystemClock:
    """The machine's clocks. `monotonic()` is the kernel's boot clock: it counts time suspended (a night in
    standby ages a recording; it is no step of the wall clock) and no one can step it. It is read through the
    C library (CLOCK_BOOTTIME: nanoseconds, 0.3 µs a reading) when that agrees with the kernel's own figure in
    /proc/uptime; tools that fake the time for a program (libfaketime, unless told to leave the monotonic
    clocks alone) move every clock the library reports, and then /proc/uptime is read instead (10 ms steps,
    3 µs). Where /proc/uptime cannot be read, `time.monotonic()`."""

    def __init__(self, uptime: str = "/proc/uptime", boot_id: str = "/proc/sys/kernel/random/boot_id"):
        self._boot_id = _read(boot_id)
        self._fd: int | None = None
        self._now = time.monotonic  # no boot clock known: the process's own monotonic clock
        try:
            self._fd = os.open(uptime, os.O_RDONLY | os.O_CLOEXEC)
            kernel = self._uptime()
        except (OSError, ValueError, IndexError):
            self._fd = None
            return
        boot = getattr(time, "CLOCK_BOOTTIME", None)
        if boot is not None and abs(time.clock_gettime(boot) - kernel) < 1.0:
            self._now = functools.partial(time.clock_gettime, boot)
        else:
            self._now = self._uptime

    def _uptime(self) -> float:
        # pread at 0 makes the kernel write the figure afresh (no open and close per reading).
        return float(os.pread(self._fd, 64, 0).split()[0])

    def monotonic(self) -> float:
        return self._now()

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

    def wait(self, waitable: Waitable, timeout: float | None) -> bool:
        return bool(waitable.wait(None if timeout is None else max(timeout, 0.0)))


def _read(path: str) -> str | None:
    try:
        with open(path) as fh:
            return fh.read().strip() or None
    except OSError:
        return None


class ManualClock:
    """A clock a test moves: `advance(s)` moves both clocks as time passing does, `step_wall(s)` moves the
    wall clock alone (an NTP step: forward when s > 0, back when s < 0). Thread-safe.

    Nothing passes on it by itself: `sleep(s)` returns once the test has advanced it `s` seconds, and `wait`
    once its waitable is set (or notified) or the test has advanced it past the timeout, so a thread waiting
    on it follows the test's steps. `idle()` says whether every thread that waits on it has caught up with the
    last step (each is waiting again, for a time still ahead): a test steps the clock, waits for `idle()`,
    and steps again, as time passing would move a service whose threads all keep up."""

    def __init__(self, wall: float = 1.7e9, monotonic: float = 1000.0, epoch: str | None = "manual",
                 slice_s: float = 0.005):
        self._moved = threading.Condition()
        self._wall = float(wall)
        self._mono = float(monotonic)
        self._epoch = epoch
        self.slice_s = float(slice_s)  # how often a wait looks at an Event (a Condition is woken by `advance`)
        self._waiting: dict[int, float] = {}  # thread id → the time it waits for (inf: only its waitable)
        self._followers: dict[int, threading.Thread] = {}  # every thread that ever waited on the clock
        self._conditions: dict[int, threading.Condition] = {}  # held Conditions waited on now, by thread

    def monotonic(self) -> float:
        with self._moved:
            return self._mono

    def wall(self) -> float:
        with self._moved:
            return self._wall

    def epoch(self) -> str | None:
        return self._epoch

    def advance(self, seconds: float) -> float:
        """Let `seconds` pass; the monotonic time after it."""
        if seconds < 0:
            raise ValueError("time passing cannot go back; step_wall steps the wall clock")
        return self._move(lambda mono: mono + seconds)

    def advance_to(self, monotonic: float) -> float:
        """Let time pass until the monotonic clock reads `monotonic` exactly (steps summed in floating point
        land a hair short of a time a sleeper computed as now + s); the monotonic time after it."""
        return self._move(lambda mono: max(mono, monotonic))

    def _move(self, to) -> float:
        with self._moved:
            new = to(self._mono)
            self._wall += new - self._mono
            self._mono = new
            self._moved.notify_all()
            conditions = list(self._conditions.values())
        for cond in conditions:  # each wait on a Condition looks at the clock again (outside our lock)
            with cond:
                cond.notify_all()
        return new

    def step_wall(self, seconds: float) -> None:
        with self._moved:
            self._wall += seconds

    def idle(self) -> bool:
        """Whether every live thread that has waited on this clock waits again for a time still ahead: none
        is running, and none is due to wake."""
        with self._moved:
            now = self._mono
            for ident, thread in list(self._followers.items()):
                if not thread.is_alive():
                    del self._followers[ident]
                    self._waiting.pop(ident, None)
                elif self._waiting.get(ident, now) <= now:
                    return False
            return True

    def _park(self, until: float, cond: threading.Condition | None = None) -> None:
        ident = threading.get_ident()
        with self._moved:
            self._followers[ident] = threading.current_thread()
            self._waiting[ident] = until
            if cond is not None:
                self._conditions[ident] = cond

    def _unpark(self) -> None:
        ident = threading.get_ident()
        with self._moved:
            self._waiting.pop(ident, None)
            self._conditions.pop(ident, None)

    def sleep(self, seconds: float) -> None:
        """Return once the clock has been advanced `seconds` from now."""
        with self._moved:
            until = self._mono + max(seconds, 0.0)
        self._park(until)
        try:
            with self._moved:
                while self._mono < until:
                    self._moved.wait()
        finally:
            self._unpark()

    def wait(self, waitable: Waitable, timeout: float | None) -> bool:
        until = float("inf") if timeout is None else self.monotonic() + max(timeout, 0.0)
        if hasattr(waitable, "is_set"):  # an Event: looked at every slice_s, woken at once by a step
            self._park(until)
            try:
                with self._moved:
                    while not waitable.is_set() and self._mono < until:
                        self._moved.wait(self.slice_s)
                return waitable.is_set()
            finally:
                self._unpark()
        # A Condition its caller holds: notified by its owner, or by a step (then the caller looks again).
        self._park(until, waitable)
        try:
            if timeout is None:
                return bool(waitable.wait())
            if self.monotonic() >= until:
                return bool(waitable.wait(0))
            return bool(waitable.wait(0.25))  # a step wakes it; the real-time bound only guards against a hang
        finally:
            self._unpark()


SYSTEM = SystemClock()
