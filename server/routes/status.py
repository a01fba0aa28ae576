"""GET /api/status: the tracker link, frame counts, the live session; GET /api/events: service events."""

from __future__ import annotations

from fastapi import APIRouter, Depends, Query, Request, Response

from flockcal.server.auth import require_read
from flockcal.server.memory import process_memory
from flockcal.server.models import Event, Status
from flockcal.server.routes.deps import MAX_ID, get_service

router = APIRouter(prefix="/api", tags=["status"])


@router.get("/status", response_model=Status, summary="tracker and pipeline status")
def get_status(request: Request, service=Depends(get_service), _role=Depends(require_read)):
    """Connected, birds, rate, frames, dropped/resynced records, reconnects, last error, live session,
    retention, the process's memory, its connections, its download slots and the live streams (VRPN, VMC)."""
    guard = getattr(request.app.state, "connection_guard", None)
    slots = getattr(request.app.state, "download_slots", None)
    return {**service.pipeline.snapshot.status, "retention": service.retention.status(), "process": process_memory(),
            "connections": guard.status() if guard is not None else None,
            "downloads": slots.status() if slots is not None else None,
            "outputs": service.outputs.status() if service.outputs is not None else None, "clock": service.clock.status()}


@router.get("/events", response_model=list[Event], summary="events of the whole service (tracker, sessions, slips)")
def get_events(response: Response,
               since: int = Query(0, ge=0, le=MAX_ID, description="only events with a larger id"),
               limit: int = Query(500, ge=1, le=5000),
               service=Depends(get_service), _role=Depends(require_read)):
    """Oldest first. When later events exist, a `Link: <…?since=N&limit=L>; rel="next"` header says
    where they are (a full page alone does not tell)."""
    events = service.store.events(None, since, limit + 1)
    if len(events) > limit:
        events = events[:limit]
        response.headers["Link"] = f'</api/events?since={events[-1].id}&limit={limit}>; rel="next"'
    return [e.doc for e in events]
