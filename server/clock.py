"""The service's clock over a `flockcal.clock.Clock`: stamps that never step back, the service time that
retention ages are counted in, and each step of the wall clock found and reported as an event. Kept in the
service's database, so stamps and service time carry on across restarts (docs/service.md, "Clock").
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass
from typing import Callable

from flockcal.clock import SYSTEM, Clock

log = logging.getLogger(__name__)

# Wall and monotonic deltas differing by more than this (or STEP_SHARE of the interval, whichever is more)
# are a step: NTP slews the wall clock by at most 500 ppm, and the boot clock reads in 10 ms steps.
STEP_S = 1.0
STEP_SHARE = 0.002
# A wall reading is bracketed by two monotonic ones; wider than this, it is read again (at most TRIES times):
# a thread descheduled between the two clocks (a loaded machine, a slow faked clock) must not look like a step.
TIGHT_S = 0.02
TRIES = 3
# After the wall clock steps back, stamps run at this share of real time until it catches up with them.
SLEW = 0.5

SCHEMA = """CREATE TABLE IF NOT EXISTS clock (
    id INTEGER PRIMARY KEY CHECK (id = 1),
    offset_s REAL NOT NULL,         -- wall clock minus service time: every step of the wall clock, summed
    service_s REAL NOT NULL,        -- service time when saved
    stamp REAL NOT NULL,            -- the latest stamp handed out (unix s)
    epoch TEXT,                     -- the monotonic clock's origin (the boot id) of `mono`
    mono REAL,                      -- the monotonic clock when saved
    steps INTEGER NOT NULL DEFAULT 0
)"""


@dataclass(frozen=True)
class Reading:
    """One look at the clock: `mono` (durations, deadlines), `wall` (as the machine has it), `stamp` (the wall
    clock that never steps back: what the service stores and shows), `service_s` (service time: ages)."""

    mono: float
    wall: float
    stamp: float
    service_s: float


class ServiceClock:
    """The clock the service's parts share (thread-safe), a `flockcal.clock.Clock` itself (monotonic time,
    sleeps and waits are the underlying clock's). `read()` looks at the underlying clock and finds
    a step of the wall clock by comparing its delta with the monotonic one: the step goes into `offset`
    (wall minus service time), so service time never moves with it; a step back holds the stamps, which then
    run at half speed until the wall clock meets them. Each step is an event for `bind`'s sink.

    With a `store` its state is loaded at start and kept by `save()`: across a restart in the same boot the
    downtime is measured on the boot clock (a step while the service was down is found too); after a reboot
    the wall clock's advance is taken as downtime, never a move back."""

    def __init__(self, clock: Clock = SYSTEM, store=None):
        self.clock = clock
        self.store = store
        self._lock = threading.Lock()
        self._sink: Callable[[dict], None] | None = None
        self._pending: list[dict] = []
        self._mono, self._wall, self._width = self._sample()
        self._stamp = self._wall
        self.offset = 0.0
        self.steps = 0
        self.last_step: dict | None = None
        self._dirty = False
        if store is not None:
            store.query(SCHEMA)
            self._restore()

    # --- the clock ----------------------------------------------------------------------------------
    def read(self) -> Reading:
        step = None
        with self._lock:
            m, w, width = self._sample()
            dm = max(m - self._mono, 0.0)
            jump = (w - self._wall) - dm
            # Each reading's wall time is known to within its bracket: the two brackets widen the bound.
            if abs(jump) > max(STEP_S, STEP_SHARE * dm) + width + self._width:
                self.offset += jump
                step = self._stepped(jump, w, while_down=False)
            # Stamps follow the wall clock forward; behind them, it is caught up slowly, never stepped back to.
            self._stamp = w if w >= self._stamp else self._stamp + SLEW * dm
            self._mono, self._wall, self._width = m, w, width
            reading = Reading(m, w, self._stamp, w - self.offset)
        if step is not None:
            self._emit(step)
        return reading

    def _sample(self) -> tuple[float, float, float]:
        """(monotonic, wall, width): the wall clock read between two monotonic readings, `monotonic` their
        midpoint and `width` the time between them; the narrowest of up to TRIES tries."""
        best = None
        for _ in range(TRIES):
            before = self.clock.monotonic()
            wall = self.clock.wall()
            after = self.clock.monotonic()
            if best is None or after - before < best[2]:
                best = (0.5 * (before + after), wall, after - before)
            if best[2] <= TIGHT_S:
                break
        return best

    def stamp(self) -> float:
        """Unix seconds for a stamp: the wall clock, never earlier than a stamp already given."""
        return self.read().stamp

    def service_s(self) -> float:
        """Service time, seconds: advances with the monotonic clock, whatever the wall clock does."""
        return self.read().service_s

    def monotonic(self) -> float:
        return self.clock.monotonic()

    def wall(self) -> float:
        return self.clock.wall()

    def epoch(self) -> str | None:
        return self.clock.epoch()

    def sleep(self, seconds: float) -> None:
        self.clock.sleep(seconds)

    def wait(self, waitable, timeout: float | None) -> bool:
        return self.clock.wait(waitable, timeout)

    def _stepped(self, jump: float, wall: float, while_down: bool) -> dict:
        self.steps += 1
        self._dirty = True
        way = "forward" if jump > 0 else "back"
        when = "while the service was not running" if while_down else "while the service ran"
        tail = "" if jump > 0 else "; stamps run at half speed until the wall clock catches up with them"
        self.last_step = {"step_s": round(jump, 3), "wall": wall, "while_down": while_down}
        message = (f"the wall clock stepped {way} by {abs(jump):.1f} s {when} (NTP, or the clock was set); "
                   f"durations, leases and retention ages are on the service's own clock and did not move{tail}")
        log.warning("%s", message)
        return {"type": "service", "action": "clock_step", "step_s": round(jump, 3), "while_down": while_down,
                "message": message}

    # --- events -------------------------------------------------------------------------------------
    def bind(self, sink: Callable[[dict], None]) -> None:
        """Send step events to `sink` (Pipeline.add_event); those found before it was bound go now."""
        with self._lock:
            self._sink, pending, self._pending = sink, self._pending, []
        for event in pending:
            sink(event)

    def _emit(self, event: dict) -> None:
        with self._lock:
            sink = self._sink
            if sink is None:
                self._pending.append(event)
                return
        sink(event)

    # --- kept across restarts -------------------------------------------------------------------------
    def _restore(self) -> None:
        rows = self.store.query("SELECT offset_s, service_s, stamp, epoch, mono, steps FROM clock WHERE id = 1")
        if not rows:
            self.save()
            return
        offset_s, service_s, stamp, saved_epoch, mono, steps = rows[0]
        step = None
        with self._lock:
            m, w = self._mono, self._wall
            epoch = self.clock.epoch()
            if saved_epoch is not None and saved_epoch == epoch and mono is not None \
                    and m >= mono:
                service = service_s + (m - mono)  # the same boot: downtime measured
            else:
                service = max(service_s, w - offset_s)  # rebooted: the wall's advance, if any
            jump = (w - offset_s) - service
            self.offset = w - service
            self.steps = int(steps)
            self._stamp = max(w, stamp)
            if abs(jump) > STEP_S:
                step = self._stepped(jump, w, while_down=True)
        if step is not None:
            self._emit(step)
        self.save()

    def save(self) -> None:
        """Keep the state in the database (a step at once: a restart must not count it as time)."""
        if self.store is None:
            return
        r = self.read()
        with self._lock:
            row = (self.offset, r.service_s, self._stamp, self.clock.epoch(), r.mono, self.steps)
            self._dirty = False
        self.store.query(
            "INSERT INTO clock (id, offset_s, service_s, stamp, epoch, mono, steps) VALUES (1, ?, ?, ?, ?, ?, ?) "
            "ON CONFLICT(id) DO UPDATE SET offset_s = excluded.offset_s, service_s = excluded.service_s, "
            "stamp = excluded.stamp, epoch = excluded.epoch, mono = excluded.mono, steps = excluded.steps", row)

    @property
    def dirty(self) -> bool:
        """A step was found since the last save."""
        return self._dirty

    def status(self) -> dict:
        """For /api/status: service time, the summed steps (`offset_s`), how far stamps run ahead of the wall
        clock, the steps found and the last of them."""
        r = self.read()
        return {"service_s": round(r.service_s, 3), "offset_s": round(self.offset, 3),
                "stamp_ahead_s": round(r.stamp - r.wall, 3), "steps": self.steps, "last_step": self.last_step}
