"""The solver's one exception type, for problems a person can fix (bad shapes, a hierarchy with a cycle)."""

from flockcal.errors import FlockcalError


class SolverError(FlockcalError, ValueError):
    """Input the solver cannot use; the message names the thing and the fix."""
