"""Shared dependencies of the routes: the running service and validated path parameters."""

from __future__ import annotations

import re

from fastapi import Path, Request

from flockcal.server.errors import BadRequest

SESSION_ID_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9\-]{0,63}")  # whole id: fullmatch ($ lets "a\n" in)
MAX_ID = 2**63 - 1  # SQLite's integers are 64-bit: a larger id is no id (and overflowed into a 500)


def get_service(request: Request):
    return request.app.state.service


def session_id(id: str = Path(description="session id, as returned by POST /api/sessions",
                              json_schema_extra={"pattern": f"^{SESSION_ID_RE.pattern}$"})) -> str:
    # Ids become file names; refuse anything that could walk out of the recordings directory. The pattern is
    # documented, not validated by FastAPI: an id that does not match is a 400 with this message, not a 422.
    if not SESSION_ID_RE.fullmatch(id):
        raise BadRequest(f"{id[:80]!r} is not a session id (letters, digits and '-' only); GET /api/sessions lists them")
    return id
