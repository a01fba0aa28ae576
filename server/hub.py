"""Hands the pipeline's newest snapshot to asyncio senders without ever making the pipeline wait.

The pipeline thread calls `publish`; it schedules a wake-up on the event loop and returns. Senders
`await wait_newer(seq)` and then read `latest` — so a slow sender simply skips snapshots.
"""

from __future__ import annotations

import asyncio

from flockcal.server.snapshot import Snapshot


class SnapshotHub:
    def __init__(self, first: Snapshot | None = None):
        self.latest = first  # the pipeline publishes its first snapshot as it is built
        self.loop: asyncio.AbstractEventLoop | None = None
        self._event: asyncio.Event | None = None
        self._scheduled = False
        self._waiting = 0  # senders parked in wait_newer: only they need the event loop woken
        self.clients = 0
        self.dropped_slow = 0  # clients dropped because they stopped reading

    def bind(self, loop: asyncio.AbstractEventLoop) -> None:
        self.loop = loop
        self._event = asyncio.Event()

    def publish(self, snapshot: Snapshot) -> None:
        """From any thread: make `snapshot` the newest and wake the senders (once per loop turn)."""
        self.latest = snapshot
        loop = self.loop
        # A sender that is not parked (a 15 Hz dashboard between its sends) reads `latest` when it wakes
        # on its own; waking the event loop for every snapshot (~100/s) would be work for nobody.
        if loop is None or self._scheduled or not self._waiting or loop.is_closed():
            return
        self._scheduled = True
        try:
            loop.call_soon_threadsafe(self._wake)
        except RuntimeError:  # loop closing during shutdown
            self._scheduled = False

    def _wake(self) -> None:
        self._scheduled = False
        event, self._event = self._event, asyncio.Event()
        event.set()

    async def wait_newer(self, seq: int, timeout: float | None = None) -> Snapshot:
        """The newest snapshot once its seq exceeds `seq` (or after `timeout` seconds, whatever it is)."""
        # Counted as waiting before `latest` is looked at: a snapshot published in between then
        # either shows in that look or finds the count up and wakes the loop (no lost wake-up).
        self._waiting += 1
        try:
            while self.latest.seq <= seq:
                event = self._event
                try:
                    async with asyncio.timeout(timeout):  # no extra task per wait, unlike wait_for
                        await event.wait()
                except TimeoutError:
                    break
        finally:
            self._waiting -= 1
        return self.latest
