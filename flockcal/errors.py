"""One base exception for everything flockcal reports to a person.

Each layer derives its own type from `FlockcalError` (SolverError, TakeError, TrackerError, …);
the command line prints any of them as one line and exits non-zero, without a traceback.
"""


class FlockcalError(Exception):
    """A problem a person can act on; the message names the thing and the fix. `exit_code` is what the
    command line exits with when it reports one (2 unless a type says otherwise)."""

    exit_code = 2


class UserError(FlockcalError):
    """Bad command-line input (a missing file, an option that makes no sense)."""
