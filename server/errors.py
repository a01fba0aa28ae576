"""Errors of the live service, each carrying the HTTP status a client should see.

Route handlers and the session manager raise these; app.py turns them into JSON
`{"detail": message, "error": code}` so a person reading the response knows what to fix.
"""

from __future__ import annotations

from flockcal.errors import FlockcalError


class ServerError(FlockcalError):
    """A problem with the service's configuration or a request; `status` is the HTTP code."""

    status = 500
    code = "server_error"

    def __init__(self, message: str, status: int | None = None, code: str | None = None):
        super().__init__(message)
        if status is not None:
            self.status = status
        if code is not None:
            self.code = code


class ConfigError(ServerError):
    """Settings that cannot work together (e.g. a public address without a token)."""

    status = 500
    code = "config_error"


class BadRequest(ServerError):
    status = 400
    code = "bad_request"


class Unauthorized(ServerError):
    status = 401
    code = "unauthorized"


class Forbidden(ServerError):
    status = 403
    code = "forbidden"


class NotFound(ServerError):
    status = 404
    code = "not_found"


class Conflict(ServerError):
    status = 409
    code = "conflict"


class Gone(ServerError):
    """The thing existed but was removed on purpose (a pruned session's frames): 410."""

    status = 410
    code = "gone"


class Unavailable(ServerError):
    """503; `retry_after` (seconds) becomes the reply's Retry-After header: every 503 says when to try again."""

    status = 503
    code = "unavailable"

    def __init__(self, message: str, retry_after: int = 5, **kw):
        super().__init__(message, **kw)
        self.retry_after = int(retry_after)


class InsufficientStorage(ServerError):
    """507: no room on the disk for what the request would write (a session's recording, a database row)."""

    status = 507
    code = "insufficient_storage"


class DatabaseDamaged(Unavailable):
    """The service's database (or a row in it) is damaged: 503 for the calls that touch it, and at start
    `flockcal serve` refuses with its own exit status (the kiosk unit does not restart it)."""

    code = "database_damaged"

    def __init__(self, message: str, retry_after: int = 60):
        super().__init__(message, retry_after=retry_after)


class TooManyAttempts(ServerError):
    """Too many unrecognised tokens from one address (server/backoff.py); `retry_after` in seconds."""

    status = 429
    code = "too_many_attempts"

    def __init__(self, message: str, retry_after: int):
        super().__init__(message)
        self.retry_after = retry_after
