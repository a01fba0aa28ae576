"""The service's OpenAPI document as the API behaves: bearer tokens as a security scheme on the operations that
need them, every error status an operation can answer (with its Retry-After / WWW-Authenticate headers), the
422 body the service sends (an ErrorReply, not FastAPI's list), and the names this service accepts.
"""

from __future__ import annotations

import copy
from contextvars import ContextVar
from dataclasses import dataclass

from fastapi import FastAPI
from fastapi.openapi.utils import get_openapi
from fastapi.routing import APIRoute

from flockcal.server.auth import require_admin, require_read, require_session_control

ERROR = {"application/json": {"schema": {"$ref": "#/components/schemas/ErrorReply"}}}
RETRY_AFTER = {"Retry-After": {"description": "seconds to wait before trying again", "required": True,
                               "schema": {"type": "integer"}}}
# Statuses every operation may answer, whatever it does.
COMMON = {
    400: ("a malformed request: a Host the service does not answer to, a bad Content-Length, a body that is "
          "not JSON, an id or name that cannot be one", None),
    422: ("the request does not match this document: `detail` names the field and what it must be "
          "(an ErrorReply, as every error)", None),
    503: ("the service cannot answer now (its database cannot be read or written, or is damaged; all download "
          "slots taken): try again after Retry-After", RETRY_AFTER),
}
WHY = {
    401: ("no bearer token, or one the service does not know", {"WWW-Authenticate": {
        "description": "Bearer", "required": True, "schema": {"type": "string"}}}),
    429: ("too many unrecognised tokens from this address: wait Retry-After seconds", RETRY_AFTER),
    403: ("a page from another site (its Origin was not given with --cors-origin), or a token whose role may not "
          "do this", None),
    409: ("the session or service is not in a state that allows it (the reason says which; a DELETE of a "
          "session being downloaded also says Retry-After)", {"Retry-After": {
              "description": "seconds to wait (a DELETE while the session is being downloaded)", "required": False,
              "schema": {"type": "integer"}}}),
}
BEARER = {"bearer": {
    "type": "http", "scheme": "bearer",
    "description": "Authorization: Bearer TOKEN — read (--read-token: GET and the websocket), kiosk "
                   "(--kiosk-token: read, start and stop sessions) or admin (--token: everything)"}}
ROLES = {require_read: "read", require_session_control: "kiosk", require_admin: "admin"}
ROLE_WORDS = {"read": "any token (--read-token, --kiosk-token or --token)",
              "kiosk": "the kiosk or admin token (--kiosk-token or --token)",
              "admin": "the admin token (--token)"}


@dataclass(frozen=True)
class Names:
    """The names this service accepts now, which its document lists: its sensors, its session presets."""

    sensors: tuple[str, ...] = ()
    presets: tuple[str, ...] = ()


# The names of the service whose document is being made (none outside `openapi_document`: fields as declared).
# The models' and routes' `json_schema_extra` hooks below read it, so pydantic writes the lists in place.
NAMES: ContextVar[Names] = ContextVar("flockcal_openapi_names", default=Names())


def _one_of(names: tuple[str, ...]) -> list[dict]:
    return [{"type": "string", "enum": list(names)}, {"type": "null"}]


def sensor_enum(schema: dict) -> None:
    """`json_schema_extra` of a field naming a sensor: one of this service's sensors."""
    if NAMES.get().sensors:
        schema["enum"] = list(NAMES.get().sensors)


def sensor_or_none(schema: dict) -> None:
    """`json_schema_extra` of an optional field naming a sensor (a joint, a root): one of the sensors or null."""
    if NAMES.get().sensors:
        schema["anyOf"] = _one_of(NAMES.get().sensors)


def preset_or_none(schema: dict) -> None:
    """`json_schema_extra` of an optional field naming a session preset: one of those saved now, or null."""
    if NAMES.get().sensors and NAMES.get().presets:
        schema["anyOf"] = _one_of(NAMES.get().presets)


def api_routes(routes) -> list[APIRoute]:
    """The API routes, those of included routers too (FastAPI includes routers lazily since 0.16x)."""
    try:
        from fastapi.openapi.utils import _get_api_route_for_openapi
        from fastapi.routing import iter_route_contexts
    except ImportError:  # a FastAPI that keeps its routes flat
        return [r for r in routes if isinstance(r, APIRoute)]
    return [r for r in map(_get_api_route_for_openapi, iter_route_contexts(routes)) if r is not None]


def route_role(route: APIRoute) -> str | None:
    """The role the route's auth dependency asks for ("read", "kiosk", "admin"), None for an open route."""
    stack = list(route.dependant.dependencies)
    role = None
    while stack:
        dep = stack.pop()
        role = ROLES.get(dep.call, role)
        stack.extend(dep.dependencies)
    return role


def documented(route: APIRoute, token_required: bool) -> APIRoute:
    """A copy of `route` (for the document only) saying what it answers on this service: the statuses any
    operation may answer, 401/429 and the bearer scheme where a token is asked for, 403 where a role or
    another site's page can be refused, the reason for a 409 it declares."""
    role = route_role(route)
    guarded = role is not None and token_required
    answers = dict(COMMON)
    if guarded:
        answers.update({401: WHY[401], 429: WHY[429]})
    if role in ("kiosk", "admin"):
        answers[403] = WHY[403]
    if 409 in route.responses:
        answers[409] = WHY[409]
    out = copy.copy(getattr(route, "original_route", route))  # FastAPI's route behind its include context
    out.responses = {**route.responses, **{
        code: {"description": why, "content": ERROR, **({"headers": headers} if headers else {})}
        for code, (why, headers) in answers.items()}}
    if guarded:
        out.description = f"Needs {ROLE_WORDS[role]}.\n\n{route.description or ''}"
        out.openapi_extra = {**(route.openapi_extra or {}), "security": [{"bearer": []}]}
    return out


def openapi_document(app: FastAPI, token_required: bool, sensors: tuple[str, ...],
                     presets: tuple[str, ...] = ()) -> dict:
    """The document of `app` as this service runs: tokens required or not, its sensors' names, the session
    presets it has now."""
    routes = [documented(route, token_required) for route in api_routes(app.routes)]
    names = NAMES.set(Names(tuple(sensors), tuple(presets)))
    try:
        doc = get_openapi(title=app.title, version=app.version, description=app.description, routes=routes)
    finally:
        NAMES.reset(names)
    if token_required:
        doc["components"]["securitySchemes"] = copy.deepcopy(BEARER)
    return doc
