"""The drivers' error type: a tracker problem a person can act on (the command line prints it as one line)."""

from flockcal.errors import FlockcalError


class TrackerError(FlockcalError):
    """A tracker problem a person can act on (no answer, wrong baud rate, a bird error, a port in use, …)."""
