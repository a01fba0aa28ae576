"""One base exception for everything flockcal reports to a person.

Each layer derives its own type from `FlockcalError` (SolverError, TakeError, TrackerError, …);
the command line prints any of them as one line and exits non-zero, without a traceback.
"""


class FlockcalError(Exception):
    """A problem a person can act on; the message names the thing and the fix. `exit_code` is what the
    command line exits with when it reports one (2 unless a type says otherwise).

    Every error flockcal raises for bad input or a failed device is one: each layer derives its own
    (`flockcal.takes.TakeError`, `flockcal.solver.errors.SolverError`, `flockcal.drivers.TrackerError`,
    `flockcal.server.ServerError`, …), so one ``except flockcal.FlockcalError`` catches them all and
    lets a bug (any other exception) through. Its one argument is the message: one line, the thing that is
    wrong and what to do about it.

    Attributes
    ----------
    exit_code : int
        What the command line exits with for it: 2 (bad input) unless a subclass says otherwise.

    Examples
    --------
    >>> import flockcal
    >>> try:
    ...     flockcal.load_take("no-such-take.npz")
    ... except flockcal.FlockcalError as exc:
    ...     print(exc, exc.exit_code)
    no-such-take.npz: no such file 2
    """

    exit_code = 2


class UserError(FlockcalError):
    """Bad command-line input (a missing file, an option that makes no sense)."""
