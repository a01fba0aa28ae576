"""Hands the pipeline's newest snapshot to asyncio senders without ever making the pipeline wait.

The pipeline thread calls `publish`; it schedules a wake-up on the event loop and returns. Senders
`await wait_newer(seq)` and then read `latest` — so a slow sender simply skips snapshots.
"""

from __future__ import annotations

import asyncio

from flockcal.server.snapshot import Snapshot


class SnapshotHub:
    def __init__(self, first: Snapshot):
        self.latest = first
        self.loop: asyncio.AbstractEventLoop | None = None
        self._event: asyncio.Event | None = None
        self._scheduled = False
        self.clients = 0
        self.dropped_slow = 0  # clients dropped because they stopped reading

    def bind(self, loop: asyncio.AbstractEventLoop) -> None:
        self.loop = loop
        self._event = asyncio.Event()

    def publish(self, snapshot: Snapshot) -> None:
        """From any thread: make `snapshot` the newest and wake the senders (once per loop turn)."""
        self.latest = snapshot
        loop = self.loop
        if loop is None or self._scheduled or loop.is_closed():
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
        while self.latest.seq <= seq:
            event = self._event
            try:
                async with asyncio.timeout(timeout):  # no extra task per wait, unlike wait_for
                    await event.wait()
            except TimeoutError:
                break
        return self.latest
