"""Who may do what: bearer tokens as FastAPI dependencies.

admin (`--token`) may do everything; kiosk (`--kiosk-token`) may read and start/stop sessions;
read (`--read-token`) may only read (GET and the websocket). With no token configured the service is
open, which `Settings.check` only allows on a loopback address.
"""

from __future__ import annotations

import math
import secrets
import urllib.parse
from typing import Literal

from fastapi import Request

from flockcal.server.errors import Forbidden, TooManyAttempts, Unauthorized
from flockcal.server.settings import Settings

Role = Literal["admin", "kiosk", "read"]


def token_role(settings: Settings, token: str | None) -> Role | None:
    """The role a presented token grants, or None; constant-time comparisons."""
    if not settings.token:
        return "admin"
    if not token:
        return None
    found: Role | None = None
    for role, expected in (("admin", settings.token), ("kiosk", settings.kiosk_token), ("read", settings.read_token)):
        if expected and secrets.compare_digest(token.encode(), expected.encode()):
            found = role
    return found


def presented_role(settings: Settings, backoff, token: str, peer: str | None) -> Role:
    """The role a presented token grants, through the failed-token back-off (server/backoff.py):
    TooManyAttempts while `peer` must wait, Unauthorized (counted as a failure) for an unknown token."""
    wait = backoff.wait_s(peer) if backoff is not None else 0.0
    if wait > 0:
        seconds = math.ceil(wait)
        raise TooManyAttempts(f"too many unrecognised tokens from {peer}; wait {seconds} s before trying again",
                              retry_after=seconds)
    role = token_role(settings, token)
    if role is None:
        if backoff is not None:
            backoff.failed(peer)
        raise Unauthorized("the token was not recognised; check the --token/--read-token/--kiosk-token the service started with")
    return role


def bearer(request: Request) -> str | None:
    header = request.headers.get("authorization", "")
    scheme, _, value = header.partition(" ")
    if scheme.lower() != "bearer" or not value.strip():
        return None
    return value.strip()


def origin_allowed(settings: Settings, headers) -> bool:
    """A browser's cross-site request (a page elsewhere posting to, or opening a socket on, this service)
    is refused unless its origin was listed with --cors-origin. Non-browser clients send no Origin."""
    origin = headers.get("origin")
    if not origin:
        return True
    if origin in settings.cors_origins:
        return True
    return urllib.parse.urlsplit(origin).netloc == headers.get("host", "")


def _check_origin(request: Request) -> None:
    if not origin_allowed(request.app.state.settings, request.headers):
        raise Forbidden(f"requests from the web page at {request.headers.get('origin')} are not allowed; "
                        "start the service with --cors-origin for that page")


def _role(request: Request) -> Role:
    settings: Settings = request.app.state.settings
    if not settings.token:
        return "admin"
    token = bearer(request)
    if token is None:
        raise Unauthorized("this service needs a token: send the header 'Authorization: Bearer <token>'")
    peer = request.client.host if request.client else None
    return presented_role(settings, getattr(request.app.state, "token_backoff", None), token, peer)


def require_read(request: Request) -> Role:
    return _role(request)


def require_session_control(request: Request) -> Role:
    _check_origin(request)
    role = _role(request)
    if role not in ("admin", "kiosk"):
        raise Forbidden("this token is read-only; starting or stopping sessions needs the admin or kiosk token")
    return role


def require_admin(request: Request) -> Role:
    _check_origin(request)
    role = _role(request)
    if role != "admin":
        raise Forbidden(f"this {role} token cannot do that; it needs the admin token (--token)")
    return role
