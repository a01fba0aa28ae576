"""Pinning a session so retention never prunes its frames and raw recording (server/retention.py)."""

from __future__ import annotations

from fastapi import APIRouter, Depends

from flockcal.server.auth import require_admin
from flockcal.server.models import ErrorReply, Session
from flockcal.server.routes.deps import get_service, session_id

router = APIRouter(prefix="/api/sessions", tags=["sessions"])
ERRORS = {code: {"model": ErrorReply} for code in (400, 401, 403, 404, 409)}


@router.post("/{id}/pin", response_model=Session, responses=ERRORS,
             summary="keep this session's frames and raw recording whatever the retention")
def pin_session(sid: str = Depends(session_id), service=Depends(get_service), _role=Depends(require_admin)):
    service.sessions.get(sid)  # 404 for an unknown id
    service.retention.pin(sid, True)
    return service.sessions.get(sid)


@router.delete("/{id}/pin", response_model=Session, responses=ERRORS,
               summary="unpin: the session's files may be pruned again")
def unpin_session(sid: str = Depends(session_id), service=Depends(get_service), _role=Depends(require_admin)):
    service.sessions.get(sid)
    service.retention.pin(sid, False)
    return service.sessions.get(sid)
