"""Sessions: list, start, read, stop, delete, result, residual time series, events, re-solve, downloads.

Handlers only validate and read: fits come from the pipeline's snapshots or the store.
"""

from __future__ import annotations

import os

from fastapi import APIRouter, Depends, Query, Request
from fastapi.responses import Response

from flockcal.server.auth import require_admin, require_read, require_session_control
from flockcal.server.errors import BadRequest, Conflict, NotFound
from flockcal.server.openapi import sensor_or_none
from flockcal.server.models import (
    CalibrationResult, ErrorReply, EventList, Lease, Progress, ResidualSeries, Session, SessionCreate, SessionList,
)
from flockcal.server.routes.deps import MAX_ID, get_service, session_id
from flockcal.server.settings import NAME_RE

router = APIRouter(prefix="/api/sessions", tags=["sessions"])

ERRORS = {code: {"model": ErrorReply} for code in (400, 401, 403, 404, 409, 410, 413, 422, 503, 507)}
MAX_RESIDUALS = 100_000  # samples per page: 83 minutes at 20 a second
MAX_EVENTS = 5000


def presets(service) -> dict[str, dict | None]:
    """Named hierarchies a session can start with: 'auto', 'human' when the sensors are the simulator's,
    and every saved skeleton (GET /api/skeletons)."""
    human = _human_tree(service.pipeline.names)
    return {"auto": None, **({"human": human} if human is not None else {}), **service.skeletons.hierarchies()}


def _human_tree(names) -> dict[str, str] | None:
    """The simulator's body's {child: parent} when `names` are its sensors, else None."""
    try:
        from flockcal.simulator.body import human

        body = human(n_bodies=len(names))
    except Exception:  # no simulator body for this sensor set: only automatic topology
        return None
    if list(body.names) != list(names):
        return None
    return {body.names[i]: body.names[p] for i, p in enumerate(body.parent) if p >= 0}


@router.get("", response_model=SessionList, summary="all sessions, newest first", responses=ERRORS)
def list_sessions(service=Depends(get_service), _role=Depends(require_read)):
    return {"sessions": service.sessions.list(), "live": service.sessions.live_id()}


@router.post("", response_model=Session, status_code=201, summary="start a session", responses=ERRORS)
def start_session(body: SessionCreate, service=Depends(get_service), _role=Depends(require_session_control)):
    """Start recording a performer: automatic topology, or a known `hierarchy` ({child: parent}) / `skeleton` preset."""
    service.limits.check_start()  # 507 when the disk is already at the service's reserve
    hierarchy = body.hierarchy
    saved = service.skeletons.get(body.skeleton) if body.skeleton is not None else None
    if saved is not None:
        if hierarchy is not None:
            raise BadRequest("give either 'hierarchy' or 'skeleton', not both")
        return service.sessions.start(body.performer, root=body.root, skeleton=saved, skeleton_name=body.skeleton,
                                      profile=body.profile, lease_s=body.lease_s)
    if body.skeleton is not None:
        if hierarchy is not None:
            raise BadRequest("give either 'hierarchy' or 'skeleton', not both")
        known = presets(service)
        if body.skeleton not in known:
            raise BadRequest(f"unknown skeleton {body.skeleton!r}; choose one of: {', '.join(known)}")
        hierarchy = known[body.skeleton]
    if hierarchy is not None:
        bad = [x for kv in hierarchy.items() for x in kv if not NAME_RE.fullmatch(x)]
        if bad:
            raise BadRequest(f"hierarchy name {bad[0][:80]!r} is not a valid sensor name")
    return service.sessions.start(body.performer, hierarchy, body.root, profile=body.profile, lease_s=body.lease_s)


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


@router.post("/{id}/lease", response_model=Lease, responses=ERRORS,
             summary="renew a live session's lease (sessions started with lease_s)")
def renew_lease(sid: str = Depends(session_id), service=Depends(get_service), _role=Depends(require_session_control)):
    """Push the session's end `lease_s` from now; 409 when it is not live or has no lease."""
    return service.sessions.renew(sid)


@router.post("/{id}/resolve", response_model=Session, responses=ERRORS,
             summary="re-fit a stopped or interrupted session from its recording")
def resolve_session(sid: str = Depends(session_id), service=Depends(get_service), _role=Depends(require_admin)):
    return service.sessions.resolve(sid)


@router.get("/{id}/result", response_model=CalibrationResult, responses=ERRORS,
            summary="the calibration, same shape as `flockcal fit --json`")
def get_result(sid: str = Depends(session_id), service=Depends(get_service), _role=Depends(require_read)):
    fit, _live = service.sessions.result(sid)
    return fit.doc  # its §5 object, made once per fit


@router.get("/{id}/progress", response_model=Progress, responses=ERRORS,
            summary="calibration progress: done, what is missing and why (the kiosk ring's figure)")
def get_progress(sid: str = Depends(session_id), service=Depends(get_service), _role=Depends(require_read)):
    """The service's one definition of progress, for the live session as it goes and for a stopped one as
    it ended. `done` is what an integration waits for; `missing` names every joint still to calibrate."""
    return service.sessions.progress(sid).to_dict()


@router.get("/{id}/residuals", response_model=ResidualSeries, responses=ERRORS,
            summary="per-joint residual rms (mm) over time, oldest first, a page at a time")
def get_residuals(sid: str = Depends(session_id),
                  joint: str | None = Query(None, max_length=64, description="a joint, named by its child body",
                                            json_schema_extra=sensor_or_none),
                  since: float | None = Query(None, allow_inf_nan=False,
                                              description="session clock, seconds: only later samples"),
                  limit: int = Query(MAX_RESIDUALS, ge=1, le=MAX_RESIDUALS, description="samples per page"),
                  service=Depends(get_service), _role=Depends(require_read)):
    """A session longer than one page (`limit` samples, 20 a second) answers `more: true`; the rest
    follows with `since=next_since`, so the newest samples are never dropped unseen."""
    rows, more = service.sessions.residuals(sid, joint, since, limit)
    names = sorted({k for _, v in rows for k in v})
    return {"session_id": sid, "joint": joint, "times": [t for t, _ in rows],
            "joints": {k: [v.get(k) for _, v in rows] for k in names},
            "more": more, "next_since": rows[-1][0] if rows else since}


@router.get("/{id}/events", response_model=EventList, responses=ERRORS,
            summary="slippage, tracker and session events, oldest first, a page at a time")
def get_events(sid: str = Depends(session_id),
               since: int = Query(0, ge=0, le=MAX_ID, description="only events with a larger id"),
               limit: int = Query(1000, ge=1, le=MAX_EVENTS, description="events per page"),
               service=Depends(get_service), _role=Depends(require_read)):
    """`more: true` when later events exist; ask again with `since=next_since` for them."""
    events = service.sessions.events(sid, since, limit + 1)
    more = len(events) > limit
    events = events[:limit]
    return {"session_id": sid, "events": [e.doc for e in events], "more": more,
            "next_since": events[-1].id if events else since}


@router.get("/{id}/take", responses={200: {"content": {"application/octet-stream": {}}}, **ERRORS},
            summary="the session's frames as a design.md §5 .npz take (what `flockcal fit` reads)")
def get_take(request: Request, sid: str = Depends(session_id), service=Depends(get_service),
             _role=Depends(require_read)):
    from flockcal.server.downloads import SlottedResponse, npz_stream

    # Streamed from the frame log a chunk at a time (server/downloads.py): memory stays bounded for a
    # session of any length. A live session's take holds the frames recorded when the download began.
    with _held(service, sid) as hold:
        frames = hold.frames()
        body = _slotted(request, lambda: npz_stream(frames), hold)
    return SlottedResponse(body, request.app.state.download_slots, media_type="application/octet-stream",
                           headers={"Content-Disposition": f'attachment; filename="{sid}.npz"'})


@router.get("/{id}/skeleton", responses={200: {"content": {"application/json": {}}}, **ERRORS},
            summary="the calibrated skeleton file (flockcal.exports.skeleton) of the session")
def get_skeleton(sid: str = Depends(session_id), service=Depends(get_service), _role=Depends(require_read)):
    from flockcal.exports.skeleton import skeleton_bytes

    headers = {"Content-Disposition": f'attachment; filename="{sid}-skeleton.json"'}
    # Built whole while the session's files are held (a DELETE meanwhile answers 409), then sent from memory.
    with _held(service, sid) as hold:
        fit, _live = service.sessions.result(sid)
        row = service.sessions.get(sid)
        kept = service.retention.kept_skeleton_path(sid)
        if not service.sessions.frames_path(sid).exists() and kept.exists():
            # Pruned (server/retention.py): the file was written from the frames before they went.
            return Response(kept.read_bytes(), media_type="application/json", headers=headers)
        frames = hold.frames()

        def make():
            # The performer names the file's preset when it is loaded back (`--skeleton`, POST /api/skeletons).
            source = {"session": sid, "performer": row.performer, "take": f"{sid}.npz",
                      "frames": int(frames.n), "rate_hz": float(frames.rate_hz)}
            # Sensors riding rigidly on their parent are placed from the recording, read a chunk at a time.
            return skeleton_bytes(fit.calibration, source=source, take=frames)

        data = _export(make)
        hold.end()
    return Response(data, media_type="application/json", headers=headers)


@router.get("/{id}/bvh", responses={200: {"content": {"text/plain": {}}}, **ERRORS},
            summary="the session's motion played through its calibration, as BVH")
def get_bvh(request: Request, sid: str = Depends(session_id),
            units: str = Query("cm", pattern="^(m|cm|mm|in)$", description="m, cm, mm or in"),
            up: str = Query("-z", pattern="^[+-]?[xyz]$", description="the tracker world's up axis: +y, +z or -z"),
            service=Depends(get_service), _role=Depends(require_read)):
    from flockcal.exports.bvh import bvh_chunks
    from flockcal.server.downloads import SlottedResponse, primed

    with _held(service, sid) as hold:
        fit, _live = service.sessions.result(sid)
        frames = hold.frames()
        # The exports' own writer, reading the frame log a chunk at a time (server/downloads.py FrameFile).
        text = bvh_chunks(fit.calibration, frames, units=units, up=up, chunk_frames=frames.play_frames)
        body = _slotted(request, lambda: _export(lambda: primed(part.encode("ascii") for part in text)), hold)
    return SlottedResponse(body, request.app.state.download_slots, media_type="text/plain",
                           headers={"Content-Disposition": f'attachment; filename="{sid}.bvh"'})


@router.get("/{id}/gltf", responses={200: {"content": {"model/gltf-binary": {}}}, **ERRORS},
            summary="the calibrated skeleton as a glTF 2.0 rig (.glb; a VRM 1.0 humanoid when the tree is "
                    "human-shaped), the session's motion as its animation")
def get_gltf(request: Request, sid: str = Depends(session_id),
             up: str = Query("-z", pattern="^[+-]?[xyz]$", description="the tracker world's up axis: +y, +z or -z"),
             rest: str = Query("tpose", pattern="^(tpose|first|sensor)$",
                               description="bind pose: a VRM 1.0 humanoid's T-pose (the take's first frame when the "
                                           "tree is not human-shaped), the take's first frame, or the sensor axes "
                                           "(the live pose's `rig`)"),
             animation: bool = Query(True, description="false: the rig alone, without the take as its animation "
                                                       "(what the pages load to drive from the live pose)"),
             service=Depends(get_service), _role=Depends(require_read)):
    """A human-shaped tree's rig is a VRM 1.0 humanoid (rest=tpose, the default): `X-Flockcal-Vrm` says
    `1.0`, or `none: <why>` when the file is the plain rig instead."""
    from flockcal.exports.gltf import glb_chunks
    from flockcal.exports.vrm import vrm_meta, vrm_plan
    from flockcal.server.downloads import OUT_BYTES, SlottedResponse, primed

    # The fit's number travels in a header (the file stays the CLI's): a page matches it with the live
    # pose's `rig.fit_seq` to know the rig it loaded is the one the stream drives ("final": the stored fit).
    with _held(service, sid) as hold:
        fit, fit_seq = service.sessions.result_seq(sid)
        result = fit.calibration
        frames = hold.frames()
        performer = service.sessions.get(sid).performer or sid
        vrm = []  # the VRM plan, made in the download's slot before the first byte (its reason goes in a header)

        def stream():
            if rest == "tpose":
                # The VRM of the session's whole take, as `flockcal fit --gltf` of its /take makes it: the live
                # fit's humanoid was found on the frames held live, a sample that differs from the take's.
                vrm.append(vrm_plan(result, frames, up, meta=vrm_meta(performer), from_take=True))
            return primed(glb_chunks(result, frames, up=up, name=sid, rest=rest, animation=animation,
                                     chunk_frames=frames.play_frames, out_bytes=OUT_BYTES, vrm=vrm[0] if vrm else None))

        body = _slotted(request, lambda: _export(stream), hold)
    vrm_header = {"X-Flockcal-Vrm": vrm[0].spec or f"none: {vrm[0].reason}".encode("ascii", "replace").decode()} \
        if vrm else {}
    headers = {"Content-Disposition": f'attachment; filename="{sid}.glb"',
               "X-Flockcal-Fit-Seq": "final" if fit_seq is None else str(fit_seq), **vrm_header}
    # In a slot like /take and /bvh: a client that stops reading a long animation is cut off after the stall time.
    return SlottedResponse(body, request.app.state.download_slots, media_type="model/gltf-binary", headers=headers)


@router.get("/{id}/trc", responses={200: {"content": {"text/plain": {}}}, **ERRORS},
            summary="the session's joint centres as TRC virtual markers (millimetres), for OpenSim")
def get_trc(request: Request, sid: str = Depends(session_id),
            up: str = Query("-z", pattern="^[+-]?[xyz]$", description="the tracker world's up axis: +y, +z or -z"),
            service=Depends(get_service), _role=Depends(require_read)):
    from flockcal.exports.trc import trc_chunks
    from flockcal.server.downloads import SlottedResponse, primed

    with _held(service, sid) as hold:
        fit, _live = service.sessions.result(sid)
        frames = hold.frames()
        # The exports' own writer, reading the frame log a chunk at a time (server/downloads.py FrameFile).
        text = trc_chunks(fit.calibration, frames, up=up, file_name=f"{sid}.trc", chunk_frames=frames.play_frames)
        body = _slotted(request, lambda: _export(lambda: primed(part.encode("utf-8") for part in text)), hold)
    return SlottedResponse(body, request.app.state.download_slots, media_type="text/plain",
                           headers={"Content-Disposition": f'attachment; filename="{sid}.trc"'})


class _Hold:
    """A download's hold on the session's files (server/holds.py: a DELETE meanwhile answers 409, retention
    passes the session by) and the frame log it opened. `end()` lets both go, once; a streamed download hands
    its hold to `_slotted`, which ends it when the body has been sent (or the client went away)."""

    def __init__(self, service, sid: str):
        self.service, self.sid = service, sid
        self._release = service.sessions.holds.hold(sid)  # 404/410 while the files are being removed
        self._frames = None
        self.kept = False  # handed on to a stream, which ends it

    def frames(self):
        self._frames = _frames(self.service, self.sid)
        return self._frames

    def end(self) -> None:
        frames, self._frames = self._frames, None
        if frames is not None:
            frames.close()
        self._release()


class _held:
    """`with _held(service, sid) as hold:` — the session held (404 when it is gone) until the block ends, or
    until the stream it was handed to has been sent."""

    def __init__(self, service, sid: str):
        self.hold = _Hold(service, sid)

    def __enter__(self) -> _Hold:
        try:
            self.hold.service.sessions.get(self.hold.sid)  # 404 once deleted
        except BaseException:
            self.hold.end()
            raise
        return self.hold

    def __exit__(self, kind, *exc) -> None:
        if kind is not None or not self.hold.kept:
            self.hold.end()


def _slotted(request: Request, make, hold: _Hold | None = None):
    """make() → a stream, built and run within one of the app's download slots (503 when all are taken);
    `hold` ends with it."""
    from flockcal.server.downloads import Slotted

    slots = request.app.state.download_slots
    slots.acquire()
    try:
        stream = make()
    except BaseException:
        slots.release()
        raise
    if hold is None:
        return slots.guard(stream)
    hold.kept = True

    def release():
        slots.release()
        hold.end()

    return Slotted(stream, release)


def _frames(service, sid: str):
    """The session's frame log opened for a chunked read; 404 without one (410 pruned), 409 while it is empty."""
    from flockcal.server.downloads import FrameFile

    service.sessions.get(sid)
    path = service.sessions.frames_path(sid)
    try:
        frames = FrameFile(path)
    except FileNotFoundError:
        service.retention.check_files(sid, "recording")  # 410 when retention pruned it
        raise NotFound(f"session {sid} has no recording on disk") from None
    except ValueError as exc:
        raise Conflict(f"session {sid}'s recording cannot be read: {exc}") from None
    if frames.n == 0:
        frames.close()
        raise Conflict(f"session {sid}'s recording holds no frames yet")
    return frames


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
def get_raw(request: Request, sid: str = Depends(session_id), service=Depends(get_service),
            _role=Depends(require_read)):
    """A live session's recording grows while it is sent: the download is the recording as it stood when
    asked, cut after its last whole chunk, with that exact Content-Length (a whole .fobraw that `flockcal
    convert` reads without --salvage). A stopped session's is its file."""
    from flockcal.server.downloads import Slotted, SlottedResponse, StallClockFileResponse

    name = f"{sid}.fobraw"
    slots = request.app.state.download_slots
    with _held(service, sid) as hold:
        path = service.sessions.raw_path(sid)
        if not path.exists():
            service.retention.check_files(sid, "raw recording")
            raise NotFound(f"session {sid} has no raw recording")
        hold.kept = True  # the response ends the hold once it has been sent
        # No slot (a file costs no build), but the slots' stall clock: a client that stops reading is cut off.
        if service.sessions.live_id() != sid:
            return StallClockFileResponse(path, slots, release=hold.end, media_type="application/octet-stream",
                                          filename=name)
        # FileResponse declares the size it saw, then sends to the end of the file: a live recording had grown
        # meanwhile, h11 refused the surplus and the client got a body cut short of what was declared.
        from flockcal.drivers.recording import intact_length

        fh = open(path, "rb")  # held open: the snapshot stays readable whatever happens to the name
        try:
            length = intact_length(path, os.fstat(fh.fileno()).st_size)
        except BaseException:
            fh.close()
            hold.end()
            raise
    return SlottedResponse(Slotted(_file_prefix(fh, length), hold.end), slots, media_type="application/octet-stream",
                           headers={"Content-Length": str(length), "Content-Disposition": f'attachment; filename="{name}"'})


def _file_prefix(fh, length: int, piece: int = 256 * 1024):
    """The first `length` bytes of the open file `fh`, a piece at a time; closes it."""
    with fh:
        left = length
        while left > 0:
            data = fh.read(min(piece, left))
            if not data:  # cannot happen to a file that only grows; ends the body short rather than hang
                return
            left -= len(data)
            yield data
