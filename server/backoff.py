"""Failed-token back-off: an address that keeps presenting unrecognised tokens must wait, longer each time.

Tokens are checked in constant time but could be guessed at network speed; after `free` failures an
address waits `base_s`, doubling per further failure up to `max_s`, and is forgotten after `forget_s`
without failures. While it waits every token it sends is refused unread, right or wrong.
"""

from __future__ import annotations

import threading
from collections import OrderedDict

from flockcal.clock import Clock


class TokenBackoff:
    def __init__(self, clock: Clock, free: int = 10, base_s: float = 1.0, max_s: float = 60.0,
                 forget_s: float = 600.0, max_peers: int = 4096):
        self.free, self.base_s, self.max_s, self.forget_s = free, base_s, max_s, forget_s
        self.max_peers = max_peers  # bounded memory whatever the number of addresses
        self.clock = clock
        self._peers: OrderedDict[str, list[float]] = OrderedDict()  # peer -> [failures, last failure, locked until]
        self._lock = threading.Lock()

    def wait_s(self, peer: str | None) -> float:
        """Seconds `peer` must wait before a token of theirs is looked at again (0: now)."""
        with self._lock:
            entry = self._entry(peer, create=False)
            return max(0.0, entry[2] - self.clock.monotonic()) if entry else 0.0

    def failed(self, peer: str | None) -> None:
        with self._lock:
            entry = self._entry(peer, create=True)
            now = self.clock.monotonic()
            entry[0] += 1
            entry[1] = now
            over = entry[0] - self.free
            if over > 0:
                entry[2] = now + min(self.max_s, self.base_s * 2.0 ** (over - 1))

    def _entry(self, peer: str | None, create: bool) -> list[float] | None:
        key = peer or "?"
        entry = self._peers.get(key)
        now = self.clock.monotonic()
        if entry is not None and now - entry[1] > self.forget_s and now >= entry[2]:
            del self._peers[key]
            entry = None
        if entry is None and create:
            entry = self._peers[key] = [0, 0.0, 0.0]
            while len(self._peers) > self.max_peers:
                self._peers.popitem(last=False)
        elif entry is not None:
            self._peers.move_to_end(key)
        return entry
