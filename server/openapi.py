"""The service's OpenAPI document as the API behaves: bearer tokens as a security scheme on the operations that
need them, every error status an operation can answer (with its Retry-After / WWW-Authenticate headers), the
422 body the service sends (an ErrorReply, not FastAPI's list), and the names this service accepts.
"""

from __future__ import annotations

import copy

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
ROLES = {require_read: "read", require_session_control: "kiosk", require_admin: "admin"}
ROLE_WORDS = {"read": "any token (--read-token, --kiosk-token or --token)",
              "kiosk": "the kiosk or admin token (--kiosk-token or --token)",
              "admin": "the admin token (--token)"}


def api_routes(routes) -> list[APIRoute]:
    """The API routes, those of included routers too (FastAPI includes routers lazily since 0.16x)."""
    try:
        from fastapi.openapi.utils import _get_api_route_for_openapi
        from fastapi.routing import iter_route_contexts
    except ImportError:  # a FastAPI that keeps its routes flat
        return [r for r in routes if isinstance(r, APIRoute)]
    return [r for r in map(_get_api_route_for_openapi, iter_route_contexts(routes)) if r is not None]


def route_roles(app: FastAPI) -> dict[tuple[str, str], str]:
    """{(path, method): the role its auth dependency asks for}, read off each route's dependencies."""
    out = {}
    for route in api_routes(app.routes):
        stack = list(route.dependant.dependencies)
        role = None
        while stack:
            dep = stack.pop()
            role = ROLES.get(dep.call, role)
            stack.extend(dep.dependencies)
        if role is not None:
            for method in route.methods:
                out[(route.path_format, method.lower())] = role
    return out


def openapi_document(app: FastAPI, token_required: bool, sensors: tuple[str, ...],
                     presets: tuple[str, ...] = ()) -> dict:
    """The document of `app` as this service runs: tokens required or not, its sensors' names, the session
    presets it has now."""
    doc = get_openapi(title=app.title, version=app.version, description=app.description, routes=app.routes)
    roles = route_roles(app)
    schemas = doc.setdefault("components", {}).setdefault("schemas", {})
    if token_required:
        doc["components"]["securitySchemes"] = {"bearer": {
            "type": "http", "scheme": "bearer",
            "description": "Authorization: Bearer TOKEN — read (--read-token: GET and the websocket), kiosk "
                           "(--kiosk-token: read, start and stop sessions) or admin (--token: everything)"}}
    for path, ops in doc.get("paths", {}).items():
        for method, op in ops.items():
            role = roles.get((path, method))
            responses = op.setdefault("responses", {})
            wanted = dict(COMMON)
            if role is not None and token_required:
                wanted.update({401: WHY[401], 429: WHY[429]})
                op["security"] = [{"bearer": []}]
                op["description"] = f"Needs {ROLE_WORDS[role]}.\n\n" + op.get("description", "")
            if role in ("kiosk", "admin"):
                wanted[403] = WHY[403]
            if "409" in responses:
                wanted[409] = WHY[409]
            for code, (why, headers) in wanted.items():
                reply = responses.setdefault(str(code), {})
                reply["description"] = why
                reply["content"] = copy.deepcopy(ERROR)
                if headers:
                    reply["headers"] = copy.deepcopy(headers)
            for reply in responses.values():  # what the routers declared, with no reason: the status's name
                reply.setdefault("description", "error")
            _patterns(op, sensors)
    for name in ("HTTPValidationError", "ValidationError"):
        schemas.pop(name, None)
    _bodies(schemas, sensors, presets)
    return doc


def _patterns(op: dict, sensors: tuple[str, ...]) -> None:
    """Query parameters naming a joint as the route checks them: one of this service's sensors (the patterns
    of ids and names are the routes' own: routes/deps.py, routes/skeletons.py)."""
    for param in op.get("parameters", []):
        if (param["in"], param["name"]) == ("query", "joint") and sensors:
            param["schema"]["anyOf"] = [{"type": "string", "enum": list(sensors)}, {"type": "null"}]


def _bodies(schemas: dict, sensors: tuple[str, ...], presets: tuple[str, ...]) -> None:
    """Request bodies naming a sensor or a preset name one this service has (none known: as declared)."""
    if not sensors:
        return
    slip = schemas.get("SlipRequest", {}).get("properties", {})
    if "sensor" in slip:
        slip["sensor"] = {**slip["sensor"], "enum": list(sensors)}
    create = schemas.get("SessionCreate", {}).get("properties", {})
    for field, names in (("root", sensors), ("skeleton", presets)):
        if field in create and names:
            create[field] = {"anyOf": [{"type": "string", "enum": list(names)}, {"type": "null"}],
                             "description": create[field].get("description", "")}
