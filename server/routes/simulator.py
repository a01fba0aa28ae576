"""Control of the built-in simulated performer (only when the device is sim://): slips and routines.

The dashboard's tests and demos use these to make something happen on purpose.
"""

from __future__ import annotations

from fastapi import APIRouter, Depends

from flockcal.errors import FlockcalError
from flockcal.server.auth import require_admin
from flockcal.server.errors import BadRequest, Conflict
from flockcal.server.models import ErrorReply, MotionRequest, SimulatorReply, SlipRequest
from flockcal.server.routes.deps import get_service

router = APIRouter(prefix="/api/simulator", tags=["simulator"])
ERRORS = {code: {"model": ErrorReply} for code in (400, 401, 403, 409, 422)}


def _simulator(service):
    sim = service.simulator
    if sim is None:
        raise Conflict("the device is not the built-in simulator; start the service with --device sim://… to use this")
    return sim


@router.post("/slip", response_model=SimulatorReply, responses=ERRORS, summary="make a sensor slide on the skin")
def slip(body: SlipRequest, service=Depends(get_service), _role=Depends(require_admin)):
    sim = _simulator(service)
    if body.sensor not in service.pipeline.names:
        raise BadRequest(f"no sensor {body.sensor!r}; the sensors are: {', '.join(service.pipeline.names)}")
    try:
        sim.inject_slip(body.sensor, body.distance_m)
    except FlockcalError as exc:
        raise BadRequest(str(exc)) from None
    return {"message": f"sensor {body.sensor} slipped by {body.distance_m * 1000:.0f} mm"}


@router.post("/motion", response_model=SimulatorReply, responses=ERRORS, summary="change the performer's routine")
def motion(body: MotionRequest, service=Depends(get_service), _role=Depends(require_admin)):
    sim = _simulator(service)
    try:
        sim.set_routine(body.routine)
    except FlockcalError as exc:
        raise BadRequest(str(exc)) from None
    return {"message": f"the performer now does the {body.routine!r} routine"}
