"""Saved skeletons: list, upload, download, delete. A saved skeleton is a session preset whose tree and
bone lengths are kept, so only the sensor placements are fitted for the performer's next take.
"""

from __future__ import annotations

import json

from fastapi import APIRouter, Depends, Path, Query, Request
from fastapi.responses import Response

from flockcal.server.auth import require_admin, require_read
from flockcal.server.errors import BadRequest, NotFound
from flockcal.server.models import NAME_PATTERN, ErrorReply
from flockcal.server.routes.deps import get_service
from flockcal.server.settings import NAME_RE

router = APIRouter(prefix="/api/skeletons", tags=["skeletons"])

ERRORS = {code: {"model": ErrorReply} for code in (400, 401, 403, 404, 409, 413, 422)}


def skeleton_name(name: str = Path(description="the skeleton's preset name (GET /api/skeletons)",
                                   json_schema_extra={"pattern": NAME_PATTERN})) -> str:
    # Names become file names in the data directory: nothing that could leave it.
    if not NAME_RE.fullmatch(name):
        raise BadRequest(f"{name[:80]!r} is not a skeleton name (letters, digits, space, _ . -)")
    return name


@router.get("", summary="saved skeletons a session can start with (`skeleton` of POST /api/sessions)")
def list_skeletons(service=Depends(get_service), _role=Depends(require_read)) -> dict:
    return {"skeletons": service.skeletons.list()}


@router.post("", status_code=201, responses=ERRORS,
             summary="upload a skeleton file (GET /api/sessions/{id}/skeleton, `flockcal skeleton`) as a preset",
             # The body is read whole (and checked against the tracker's sensors), not by a model: said here.
             openapi_extra={"requestBody": {"required": True, "description": "a skeleton file's JSON",
                                            "content": {"application/json": {"schema": {"type": "object"}}}}})
async def upload_skeleton(request: Request,
                          name: str | None = Query(None, pattern=NAME_PATTERN,
                                                   description="preset name; default: the file's performer"),
                          replace: bool = Query(False, description="overwrite a saved skeleton of that name"),
                          service=Depends(get_service), _role=Depends(require_admin)) -> dict:
    """The body is the skeleton JSON itself. It must name exactly the tracker's sensors; it is kept in
    the data directory, so it survives restarts."""
    body = await request.body()
    if not body.strip():
        raise BadRequest("send the skeleton file's JSON as the request body")
    return service.skeletons.upload(body, name, replace)


@router.get("/{name}", responses={200: {"content": {"application/json": {}}}, **ERRORS},
            summary="one saved skeleton file")
def get_skeleton(name: str = Depends(skeleton_name), service=Depends(get_service), _role=Depends(require_read)):
    skel = service.skeletons.get(name)
    if skel is None:
        raise NotFound(f"no skeleton {name!r}; GET /api/skeletons lists them")
    return Response(json.dumps(skel.data, indent=1) + "\n", media_type="application/json")


@router.delete("/{name}", status_code=204, responses=ERRORS, summary="delete an uploaded skeleton")
def delete_skeleton(name: str = Depends(skeleton_name), service=Depends(get_service), _role=Depends(require_admin)):
    service.skeletons.delete(name)
    return Response(status_code=204)
