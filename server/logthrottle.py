"""The service's log under a flood of the same error: each kind of warning or error is written at most once
per interval, the next one saying how many were held back; a client's fault is one line, no traceback.

Without it, descriptors running out wrote a traceback per refused accept (77–104 MB in 45 s), and every
websocket text frame that was not UTF-8 wrote six lines. `flockcal serve` puts one `LogThrottle` on every
handler (its own and uvicorn's).
"""

from __future__ import annotations

import logging
import re

from flockcal.clock import Clock

INTERVAL_S = 60.0
MAX_KINDS = 1000  # kinds remembered at once (messages that differ only in their numbers are one kind)

# Messages that report what a client did wrong, as uvicorn writes them: one line each, never a traceback.
CLIENT_FAULTS = {
    "Invalid UTF-8 sequence received from client.":
        "a websocket client sent a text frame that is not UTF-8; its connection was closed with 1007",
}


def kind_of(record: logging.LogRecord) -> tuple:
    """What makes two records "the same error": logger, level and the message with its numbers blanked."""
    try:
        text = record.getMessage()
    except Exception:  # a malformed record is still one kind
        text = str(record.msg)
    return record.name, record.levelno, re.sub(r"\d+", "#", text)[:200]


class LogThrottle(logging.Filter):
    """A handler filter: warnings and errors of one kind pass once per `interval_s`."""

    def __init__(self, clock: Clock, interval_s: float = INTERVAL_S):
        super().__init__()
        self.interval_s = float(interval_s)
        self.clock = clock
        self._kinds: dict[tuple, list] = {}  # kind -> [time it was last written, records held back since]

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno < logging.WARNING:
            return True
        plain = CLIENT_FAULTS.get(str(record.msg))
        if plain is not None:
            record.msg, record.args = plain, ()
            record.exc_info, record.exc_text, record.stack_info = None, None, None
        kind = kind_of(record)
        now = self.clock.monotonic()
        seen = self._kinds.get(kind)
        if seen is not None and now - seen[0] < self.interval_s:
            seen[1] += 1
            return False
        if len(self._kinds) >= MAX_KINDS:
            self._kinds = {k: v for k, v in self._kinds.items() if now - v[0] < self.interval_s}
        self._kinds[kind] = [now, 0]
        if seen is not None:
            # Its traceback was written the first time; later ones say how many were held back.
            record.exc_info, record.exc_text, record.stack_info = None, None, None
            if seen[1]:
                record.msg = f"{record.getMessage()} [{seen[1]} more like this in the last {now - seen[0]:.0f} s]"
                record.args = ()
        return True


def throttle_all_handlers(clock: Clock) -> LogThrottle:
    """Put a throttle on `clock` on every handler configured now: the root logger's and those of named
    loggers (uvicorn configures its own)."""
    throttle = LogThrottle(clock)
    loggers = [logging.getLogger()] + [x for x in logging.Logger.manager.loggerDict.values()
                                       if isinstance(x, logging.Logger)]
    for logger in loggers:
        for handler in logger.handlers:
            if throttle not in handler.filters:
                handler.addFilter(throttle)
    return throttle
