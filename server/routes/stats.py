"""GET /api/stats: the season at a glance for operators (server/stats.py)."""

from __future__ import annotations

from fastapi import APIRouter, Depends, Query

from flockcal.server.auth import require_read
from flockcal.server.routes.deps import get_service
from flockcal.server.stats import season

router = APIRouter(prefix="/api", tags=["status"])


@router.get("/stats", summary="sessions, finished calibrations, median time to calibrate and slips per day; disk use")
def get_stats(days: int = Query(14, ge=1, le=366, description="how many days back, today included"),
              service=Depends(get_service), _role=Depends(require_read)) -> dict:
    return season(service.store, service.data_dir, days, service.retention.policy.keep_bytes, now=service.clock.stamp())
