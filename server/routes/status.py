"""GET /api/status: the tracker link, frame counts, the live session; GET /api/events: service events."""

from __future__ import annotations

from fastapi import APIRouter, Depends, Query

from flockcal.server.auth import require_read
from flockcal.server.models import Event, Status
from flockcal.server.routes.deps import get_service

router = APIRouter(prefix="/api", tags=["status"])


@router.get("/status", response_model=Status, summary="tracker and pipeline status")
def get_status(service=Depends(get_service), _role=Depends(require_read)):
    """Connected, birds, rate, frames, dropped/resynced records, reconnects, last error, live session."""
    return {**service.pipeline.snapshot.status, "retention": service.retention.status()}


@router.get("/events", response_model=list[Event], summary="events of the whole service (tracker, sessions, slips)")
def get_events(since: int = Query(0, ge=0, description="only events with a larger id"),
               limit: int = Query(500, ge=1, le=5000),
               service=Depends(get_service), _role=Depends(require_read)):
    return service.store.events(None, since, limit)
