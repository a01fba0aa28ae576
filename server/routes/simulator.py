"""Control of the built-in simulated performer (only when the device is sim://): slips and routines.

The dashboard's tests and demos use these to make something happen on purpose.
"""

from __future__ import annotations

import time

from fastapi import APIRouter, Depends

from flockcal.errors import FlockcalError
from flockcal.server.auth import require_admin, require_read
from flockcal.server.errors import BadRequest, Conflict
from flockcal.server.models import ErrorReply, MotionRequest, SimulatorReply, SimulatorState, SlipReply, SlipRequest
from flockcal.server.routes.deps import get_service

router = APIRouter(prefix="/api/simulator", tags=["simulator"])
ERRORS = {code: {"model": ErrorReply} for code in (400, 401, 403, 409, 422)}


def _simulator(service):
    sim = service.simulator
    if sim is None:
        raise Conflict("the device is not the built-in simulator; start the service with --device sim://… to use this")
    return sim


@router.get("", response_model=SimulatorState, responses=ERRORS, summary="the simulated performer's routine and clock")
def state(service=Depends(get_service), _role=Depends(require_read)):
    """What the performer does and where it is in its routine: schedule slips on its clock
    (`POST /api/simulator/slip` with `at_routine_s`), so they land on a chosen moment of the routine."""
    sim = _simulator(service)
    motion = sim.motion
    return {"routine": motion.name, "period_s": float(motion.period), "clock_s": round(sim.clock_s, 4),
            "seed": sim.seed, "sta_mm": sim.sta_mm, "slips": sim.slips}


@router.post("/slip", response_model=SlipReply, responses=ERRORS, summary="make a sensor slide on the skin")
def slip(body: SlipRequest, service=Depends(get_service), _role=Depends(require_admin)):
    sim = _simulator(service)
    if body.sensor not in service.pipeline.names:
        raise BadRequest(f"no sensor {body.sensor!r}; the sensors are: {', '.join(service.pipeline.names)}")
    if body.at_routine_s is not None:
        try:
            ev = sim.inject_slip(body.sensor, body.distance_m, at_time=body.at_routine_s, unstreamed=True)
        except FlockcalError as exc:
            raise Conflict(str(exc)) from None
    else:
        try:
            ev = sim.inject_slip(body.sensor, body.distance_m)
        except FlockcalError as exc:
            raise BadRequest(str(exc)) from None
    routine_s = ev.time_s  # the slip's moment on the performer's clock
    clock = getattr(service.source, "reader_time", None)
    reader_time = clock(routine_s) if clock is not None else None
    # Seconds from now to the slip's sample: the simulator computes poses up to 0.1 s ahead.
    in_s = None if reader_time is None else round(reader_time - time.monotonic(), 4)
    session_id, at_s = _session_time(service.pipeline.live, reader_time)
    when = f" at {at_s:.3f} s into session {session_id}" if at_s is not None else ""
    return {"message": f"sensor {body.sensor} slipped by {body.distance_m * 1000:.0f} mm{when}",
            "sensor": body.sensor, "distance_m": body.distance_m, "session_id": session_id, "at_s": at_s,
            "in_s": in_s, "routine_s": round(routine_s, 4)}


def _session_time(live, reader_time: float | None) -> tuple[str | None, float | None]:
    """(live session id, the slip's sample time in its session time); Nones where there is none.

    Read off the pipeline thread without waiting for it (a loaded pipeline must not delay the slip's
    reply): a session's id and its live calibration's t0 (the reader time of its first frame) are each
    written once, before and on its first frame, and never change."""
    if live is None:
        return None, None
    t0 = live.cal.t0 if live.cal is not None else None
    if t0 is None or reader_time is None:
        return live.id, None
    return live.id, round(reader_time - t0, 4)


@router.post("/motion", response_model=SimulatorReply, responses=ERRORS, summary="change the performer's routine")
def motion(body: MotionRequest, service=Depends(get_service), _role=Depends(require_admin)):
    sim = _simulator(service)
    try:
        sim.set_routine(body.routine)
    except FlockcalError as exc:
        raise BadRequest(str(exc)) from None
    return {"message": f"the performer now does the {body.routine!r} routine"}
