"""Sessions: list, start, read, stop, delete, result, residual time series, events, re-solve, downloads.

Handlers only validate and read: fits come from the pipeline's snapshots or the store.
"""

from __future__ import annotations

import io

import numpy as np
from fastapi import APIRouter, Depends, Query
from fastapi.responses import Response

from flockcal.server.auth import require_admin, require_read, require_session_control
from flockcal.server.errors import BadRequest, Conflict, NotFound
from flockcal.server.models import (
    CalibrationResult, ErrorReply, EventList, Progress, ResidualSeries, Session, SessionCreate, SessionList,
)
from flockcal.server.routes.deps import get_service, session_id
from flockcal.server.settings import NAME_RE

router = APIRouter(prefix="/api/sessions", tags=["sessions"])

ERRORS = {code: {"model": ErrorReply} for code in (400, 401, 403, 404, 409, 410, 413, 422)}


def presets(service) -> dict[str, dict | None]:
    """Named hierarchies a session can start with: 'auto', 'human' when the sensors are the simulator's,
    and every saved skeleton (GET /api/skeletons)."""
    out: dict[str, dict | None] = {"auto": None}
    try:
        from flockcal.simulator.body import human

        truth = human(n_bodies=len(service.pipeline.names)).truth()
        if list(truth["sensors"]) == list(service.pipeline.names):
            out["human"] = dict(truth["parent"])
    except Exception:  # no simulator body for this sensor set: only automatic topology
        pass
    out.update(service.skeletons.hierarchies())
    return out


@router.get("", response_model=SessionList, summary="all sessions, newest first", responses=ERRORS)
def list_sessions(service=Depends(get_service), _role=Depends(require_read)):
    return {"sessions": service.sessions.list(), "live": service.sessions.live_id()}


@router.post("", response_model=Session, status_code=201, summary="start a session", responses=ERRORS)
def start_session(body: SessionCreate, service=Depends(get_service), _role=Depends(require_session_control)):
    """Start recording a performer: automatic topology, or a known `hierarchy` ({child: parent}) / `skeleton` preset."""
    hierarchy = body.hierarchy
    saved = service.skeletons.get(body.skeleton) if body.skeleton is not None else None
    if saved is not None:
        if hierarchy is not None:
            raise BadRequest("give either 'hierarchy' or 'skeleton', not both")
        return service.sessions.start(body.performer, root=body.root, skeleton=saved, skeleton_name=body.skeleton)
    if body.skeleton is not None:
        if hierarchy is not None:
            raise BadRequest("give either 'hierarchy' or 'skeleton', not both")
        known = presets(service)
        if body.skeleton not in known:
            raise BadRequest(f"unknown skeleton {body.skeleton!r}; choose one of: {', '.join(known)}")
        hierarchy = known[body.skeleton]
    if hierarchy is not None:
        bad = [x for kv in hierarchy.items() for x in kv if not NAME_RE.match(x)]
        if bad:
            raise BadRequest(f"hierarchy name {bad[0][:80]!r} is not a valid sensor name")
    return service.sessions.start(body.performer, hierarchy, body.root)


@router.get("/presets", summary="named hierarchies a session can start with")
def list_presets(service=Depends(get_service), _role=Depends(require_read)) -> dict[str, dict[str, str] | None]:
    return presets(service)


@router.get("/{id}", response_model=Session, responses=ERRORS)
def get_session(sid: str = Depends(session_id), service=Depends(get_service), _role=Depends(require_read)):
    return service.sessions.get(sid)


@router.delete("/{id}", status_code=204, responses=ERRORS, summary="delete a stopped session, its results and recordings")
def delete_session(sid: str = Depends(session_id), service=Depends(get_service), _role=Depends(require_admin)):
    service.sessions.delete(sid)
    return Response(status_code=204)


@router.post("/{id}/stop", response_model=Session, responses=ERRORS, summary="stop the live session and store its result")
def stop_session(sid: str = Depends(session_id), service=Depends(get_service), _role=Depends(require_session_control)):
    return service.sessions.stop(sid)


@router.post("/{id}/resolve", response_model=Session, responses=ERRORS,
             summary="re-fit a stopped or interrupted session from its recording")
def resolve_session(sid: str = Depends(session_id), service=Depends(get_service), _role=Depends(require_admin)):
    return service.sessions.resolve(sid)


@router.get("/{id}/result", response_model=CalibrationResult, responses=ERRORS,
            summary="the calibration, same shape as `flockcal fit --json`")
def get_result(sid: str = Depends(session_id), service=Depends(get_service), _role=Depends(require_read)):
    result, _live = service.sessions.result(sid)
    return result


@router.get("/{id}/progress", response_model=Progress, responses=ERRORS,
            summary="calibration progress: done, what is missing and why (the kiosk ring's figure)")
def get_progress(sid: str = Depends(session_id), service=Depends(get_service), _role=Depends(require_read)):
    """The service's one definition of progress, for the live session as it goes and for a stopped one as
    it ended. `done` is what an integration waits for; `missing` names every joint still to calibrate."""
    return service.sessions.progress(sid)


@router.get("/{id}/residuals", response_model=ResidualSeries, responses=ERRORS,
            summary="per-joint residual rms (mm) over time")
def get_residuals(sid: str = Depends(session_id),
                  joint: str | None = Query(None, max_length=64, description="a joint, named by its child body"),
                  since: float | None = Query(None, description="session clock, seconds: only later samples"),
                  service=Depends(get_service), _role=Depends(require_read)):
    rows = service.sessions.residuals(sid, joint, since)
    names = sorted({k for _, v in rows for k in v})
    return {"session_id": sid, "joint": joint, "times": [t for t, _ in rows],
            "joints": {k: [v.get(k) for _, v in rows] for k in names}}


@router.get("/{id}/events", response_model=EventList, responses=ERRORS, summary="slippage, tracker and session events")
def get_events(sid: str = Depends(session_id), since: int = Query(0, ge=0, description="only events with a larger id"),
               service=Depends(get_service), _role=Depends(require_read)):
    return {"session_id": sid, "events": service.sessions.events(sid, since)}


@router.get("/{id}/take", responses={200: {"content": {"application/octet-stream": {}}}, **ERRORS},
            summary="the session's frames as a design.md §5 .npz take (what `flockcal fit` reads)")
def get_take(sid: str = Depends(session_id), service=Depends(get_service), _role=Depends(require_read)):
    take = service.sessions.take(sid)
    buf = io.BytesIO()
    np.savez_compressed(buf, rotations=take.rotations, positions=take.positions,
                        names=np.asarray(take.names, dtype=str), rate_hz=np.float64(take.rate_hz),
                        valid=take.valid, times=take.times)
    return Response(buf.getvalue(), media_type="application/octet-stream",
                    headers={"Content-Disposition": f'attachment; filename="{sid}.npz"'})


@router.get("/{id}/skeleton", responses={200: {"content": {"application/json": {}}}, **ERRORS},
            summary="the calibrated skeleton file (flockcal.exports.skeleton) of the session")
def get_skeleton(sid: str = Depends(session_id), service=Depends(get_service), _role=Depends(require_read)):
    from flockcal.exports.skeleton import skeleton_bytes

    result, _live = service.sessions.result(sid)
    row = service.sessions.get(sid)
    kept = service.retention.kept_skeleton_path(sid)
    if not service.sessions.frames_path(sid).exists() and kept.exists():
        # Pruned (server/retention.py): the file was written from the frames before they went.
        return Response(kept.read_bytes(), media_type="application/json",
                        headers={"Content-Disposition": f'attachment; filename="{sid}-skeleton.json"'})

    def make():
        take = service.sessions.take(sid)
        # The performer names the file's preset when it is loaded back (`--skeleton`, POST /api/skeletons).
        source = {"session": sid, "performer": row["performer"], "take": f"{sid}.npz",
                  "frames": int(take.n_frames), "rate_hz": float(take.rate_hz)}
        return skeleton_bytes(result, source=source, take=take)

    data = _export(make)
    return Response(data, media_type="application/json",
                    headers={"Content-Disposition": f'attachment; filename="{sid}-skeleton.json"'})


@router.get("/{id}/bvh", responses={200: {"content": {"text/plain": {}}}, **ERRORS},
            summary="the session's motion played through its calibration, as BVH")
def get_bvh(sid: str = Depends(session_id),
            units: str = Query("cm", pattern="^(m|cm|mm|in)$"),
            up: str = Query("-z", pattern="^[+-]?[xyz]$", description="the tracker world's up axis"),
            service=Depends(get_service), _role=Depends(require_read)):
    from flockcal.exports.bvh import bvh_bytes

    result, _live = service.sessions.result(sid)
    data = _export(lambda: bvh_bytes(result, service.sessions.take(sid), units=units, up=up))
    return Response(data, media_type="text/plain",
                    headers={"Content-Disposition": f'attachment; filename="{sid}.bvh"'})


def _export(make):
    from flockcal.errors import FlockcalError
    from flockcal.server.errors import ServerError

    try:
        return make()
    except ServerError:
        raise
    except FlockcalError as exc:
        raise Conflict(f"cannot export this session: {exc}") from None


@router.get("/{id}/raw", responses={200: {"content": {"application/octet-stream": {}}}, **ERRORS},
            summary="the raw tracker bytes (.fobraw) of the session, when the driver recorded them")
def get_raw(sid: str = Depends(session_id), service=Depends(get_service), _role=Depends(require_read)):
    from fastapi.responses import FileResponse

    service.sessions.get(sid)
    path = service.sessions.raw_path(sid)
    if not path.exists():
        service.retention.check_files(sid, "raw recording")
        raise NotFound(f"session {sid} has no raw recording")
    return FileResponse(path, media_type="application/octet-stream", filename=f"{sid}.fobraw")
