"""The FastAPI application: routers, error replies a person can act on, body limits, CORS, pages.

`create_app(settings)` builds the app and its Service (started and stopped by the app's lifespan);
`flockcal serve` runs it under uvicorn, tests run it on a free loopback port.
"""

from __future__ import annotations

import asyncio
import json
import logging
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Annotated, Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.middleware.cors import CORSMiddleware
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse, Response
from fastapi.staticfiles import StaticFiles
from fastapi_offline import FastAPIOffline
from pydantic import BaseModel, BeforeValidator, TypeAdapter
from starlette.datastructures import MutableHeaders
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import ClientDisconnect

from flockcal import __version__
from flockcal.clock import SYSTEM, Clock
from flockcal.names import BODY_JOINTS
from flockcal.server.errors import ServerError
from flockcal.server.backoff import TokenBackoff
from flockcal.server.downloads import DownloadSlots
from flockcal.server.hosts import HostCheck, HostPolicy
from flockcal.server.wsgate import ClientSlots, TransportHandle
from flockcal.server.settings import Settings

log = logging.getLogger(__name__)

STATIC = Path(__file__).with_name("static")
DOCS_ASSETS = "/static-docs"  # where Swagger UI's and ReDoc's scripts are served from

PLACEHOLDER = """<!doctype html><meta charset="utf-8"><title>flockcal</title>
<h1>flockcal is running</h1><p>The {what} page is not installed. The API is described at
<a href="/docs">/docs</a>; live data streams from <code>/ws/live</code>.</p>"""


def names_module() -> str:
    """flockcal.names' joint-name table as the ES module the pages import (/static/names.js): one table
    names the joints for the progress hints and the pages' labels alike; and the humanoid bones in words
    (solver/humanoid.py's `bone_words`: "leftLowerArm" → "left forearm"), which body each sensor was found on."""
    from flockcal.solver.humanoid import BONES, bone_words

    rows = ",\n".join(f"  [new RegExp({json.dumps(p)}), {json.dumps(j)}, {r}]" for p, j, r in BODY_JOINTS)
    head = "// Made by the service from flockcal/names.py: body keyword, its joint, how far out it sits."
    words = json.dumps({b: bone_words(b) for b in BONES}, indent=1)
    return (f"{head}\nexport const BODY_JOINTS = [\n{rows},\n];\n"
            f"// Made from solver/humanoid.py: each humanoid bone (VRM 1.0 name) in words.\n"
            f"export const BONE_WORDS = {words};\n")


def _allowed(request: Request) -> str:
    """The methods the request's path takes, over every route of it (the router names only the first's)."""
    from starlette.routing import Match

    from flockcal.server.openapi import api_routes

    matched = [r for r in api_routes(request.app.router.routes) if r.matches(request.scope)[0] != Match.NONE]
    # A path of its own (/api/sessions/presets) is that resource, not an {id} the wider routes would take.
    literal = [r for r in matched if "{" not in r.path_format]
    return ", ".join(sorted({m for r in (literal or matched) for m in (r.methods or ())}))


def _error(status: int, message: str, code: str, headers: dict | None = None) -> JSONResponse:
    return JSONResponse({"detail": message, "error": code}, status_code=status, headers=headers)


def _validation_message(exc: RequestValidationError) -> tuple[int, str]:
    errors = PROBLEMS.validate_python(exc.errors())
    for e in errors:
        if e.type == "json_invalid":
            return 400, f"the request body is not valid JSON ({e.ctx.get('error', 'parse error')}); send a JSON object"
    parts = []
    for e in errors[:5]:
        loc = ".".join(str(x) for x in e.loc if x != "body") or "body"
        msg = e.msg
        if e.type == "extra_forbidden":
            msg = "unknown field; remove it (see /docs for the fields this request takes)"
        elif e.type == "string_pattern_mismatch":
            msg = _pattern_message(loc, e)
        parts.append(f"{loc}: {msg}")
    more = f" (and {len(errors) - 5} more)" if len(errors) > 5 else ""
    return 422, "invalid request — " + "; ".join(parts) + more


class _Problem(BaseModel):
    """One of pydantic's validation errors (its ErrorDetails; FastAPI hands them over as dicts), read once."""

    type: str | None = None
    loc: tuple[Any, ...] = ()
    msg: str = "invalid"
    input: Any = None
    # What the error type adds (the pattern, the JSON parser's message); none: empty.
    ctx: Annotated[dict[str, Any], BeforeValidator(lambda ctx: ctx or {})] = {}


PROBLEMS = TypeAdapter(list[_Problem])


def _pattern_message(loc: str, error: _Problem) -> str:
    """What a field that failed its pattern must look like: its own rule, not every field's."""
    from flockcal.server.settings import NAME_RULE, PERFORMER_RULE

    field = loc.rsplit(".", 1)[-1]
    if field == "performer":
        return f"is not allowed: a performer name is {PERFORMER_RULE}"
    if field in ("root", "skeleton", "sensor", "name"):
        return f"is not allowed: a {field} name is {NAME_RULE}"
    shown = repr(error.input)[:40]
    return f"{shown} is not allowed; it must match {error.ctx.get('pattern', 'its pattern')} (see /docs)"


class BodyLimit:
    """Refuse request bodies over `limit` bytes with 413, whether Content-Length says so or not."""

    def __init__(self, app, limit: int):
        self.app = app
        self.limit = limit

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        request = Request(scope, receive)
        length = request.headers.get("content-length")
        too_big = _error(413, f"request body too large (limit {self.limit} bytes)", "too_large")
        if length is not None:
            try:
                if int(length) > self.limit:
                    return await too_big(scope, receive, send)
            except ValueError:
                return await _error(400, "bad Content-Length header", "bad_request")(scope, receive, send)
        if request.method in ("GET", "HEAD", "OPTIONS", "DELETE") and length is None:
            return await self.app(scope, receive, send)
        # Read the body here, whatever the headers claim (chunked uploads have no length), stopping
        # past the limit, then hand it to the app in one piece.
        chunks, seen = [], 0
        try:
            async for chunk in request.stream():
                seen += len(chunk)
                if seen > self.limit:
                    return await too_big(scope, receive, send)
                chunks.append(chunk)
        except ClientDisconnect:
            return
        body = b"".join(chunks)
        sent = False

        async def replay():
            nonlocal sent
            if not sent:
                sent = True
                return {"type": "http.request", "body": body, "more_body": False}
            return await receive()

        await self.app(scope, replay, send)


# The docs pages may load only what the service serves: ReDoc's bundle would fetch its "powered by" logo
# from its makers' CDN, which an offline kiosk cannot reach (the browser now refuses it without asking the
# network). Inline scripts and styles stay allowed: the pages are FastAPI's, built that way.
DOCS_POLICY = ("default-src 'self'; script-src 'self' 'unsafe-inline'; style-src 'self' 'unsafe-inline'; "
               "img-src 'self' data:; font-src 'self' data:; worker-src 'self' blob:; connect-src 'self'")


class DocsPolicy:
    """Add DOCS_POLICY as the Content-Security-Policy of the API docs pages."""

    def __init__(self, app, paths: tuple[str, ...]):
        self.app = app
        self.paths = paths

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http" or scope.get("path") not in self.paths:
            return await self.app(scope, receive, send)

        async def with_policy(message):
            if message["type"] == "http.response.start":
                MutableHeaders(scope=message).append("content-security-policy", DOCS_POLICY)
            await send(message)

        await self.app(scope, receive, with_policy)


def create_app(settings: Settings, service=None, clock: Clock = SYSTEM) -> FastAPI:
    """The app; `service` may be given (tests), else one is built from `settings` at startup on `clock`
    (a given service's clock is the app's)."""
    from flockcal.server.routes import live, retention, sessions, simulator, skeletons, stats, status
    from flockcal.server.service import Service

    settings = settings.check()
    clock = service.clock if service is not None else clock

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        svc = service or Service(settings, clock=clock)
        app.state.service = svc
        svc.hub.bind(asyncio.get_running_loop())
        if not svc.started:
            svc.start()
        try:
            yield
        finally:
            await asyncio.get_running_loop().run_in_executor(None, svc.stop)

    # FastAPI's own /docs and /redoc load Swagger UI and ReDoc from a CDN, a blank page on an offline
    # kiosk; fastapi-offline serves the same pages from assets in its installed package.
    app: FastAPI = FastAPIOffline(
        title="flockcal",
        version=__version__,
        description="Live skeleton calibration for 6-DOF magnetic trackers. "
                    "Live data: websocket /ws/live (protocol: docs/service.md#websocket-wslive in the flockcal repository).",
        lifespan=lifespan,
        static_url=DOCS_ASSETS,
        # Swagger UI would otherwise ask validator.swagger.io for a badge about the spec.
        swagger_ui_parameters={"validatorUrl": None},
    )
    app.state.settings = settings
    app.state.token_backoff = TokenBackoff(clock)
    app.state.ws_slots = ClientSlots(settings.ws_max_clients)
    app.state.download_slots = DownloadSlots(settings.max_downloads, settings.download_stall_s)

    @app.exception_handler(ServerError)
    async def _server_error(request: Request, exc: ServerError):
        headers = {"WWW-Authenticate": "Bearer"} if exc.status == 401 else None
        if getattr(exc, "retry_after", None) is not None:
            headers = {"Retry-After": str(exc.retry_after)}
        return _error(exc.status, str(exc), exc.code, headers)

    @app.exception_handler(RequestValidationError)
    async def _invalid(request: Request, exc: RequestValidationError):
        status, message = _validation_message(exc)
        return _error(status, message, "invalid_json" if status == 400 else "invalid_request")

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException):
        if exc.status_code == 404:
            return _error(404, f"no such path {request.url.path}; the API is listed at /docs", "not_found")
        if exc.status_code == 405:
            # With the Allow header the router names (RFC 9110 §15.5.6): what the path does take.
            return _error(405, f"{request.method} is not allowed on {request.url.path}; see /docs", "method_not_allowed",
                          {"Allow": _allowed(request)})
        return _error(exc.status_code, str(exc.detail), "http_error", exc.headers)

    app.include_router(status.router)
    app.include_router(sessions.router)
    app.include_router(retention.router)
    app.include_router(stats.router)
    app.include_router(skeletons.router)
    app.include_router(simulator.router)
    app.include_router(live.router)

    def openapi() -> dict:
        # As the API behaves now (server/openapi.py): its sensors' names and the presets saved so far are part
        # of it, so it is made afresh for each request of it (tens of ms; not a hot path).
        from flockcal.server.openapi import openapi_document

        svc = getattr(app.state, "service", None)
        return openapi_document(app, settings.auth_required, tuple(svc.pipeline.names) if svc else (),
                                tuple(sessions.presets(svc)) if svc else ())

    app.openapi = openapi

    def page(name: str, what: str):
        path = STATIC / name

        async def serve_page():
            if path.exists():
                return FileResponse(path, media_type="text/html")
            return HTMLResponse(PLACEHOLDER.format(what=what))

        return serve_page

    async def names_script():
        return Response(names_module(), media_type="text/javascript")

    app.add_api_route("/", page("index.html", "dashboard"), include_in_schema=False, methods=["GET"])
    # Before the static mount, which would answer 404 for a file that is not there.
    app.add_api_route("/static/names.js", names_script, include_in_schema=False, methods=["GET"])
    app.add_api_route("/kiosk", page("kiosk.html", "kiosk"), include_in_schema=False, methods=["GET"])
    if STATIC.is_dir():
        app.mount("/static", StaticFiles(directory=STATIC), name="static")

    if settings.cors_origins:
        app.add_middleware(
            CORSMiddleware, allow_origins=list(settings.cors_origins), allow_methods=["GET", "POST", "DELETE"],
            allow_headers=["Authorization", "Content-Type"],
        )
    app.add_middleware(BodyLimit, limit=settings.max_body_bytes)
    app.add_middleware(DocsPolicy, paths=("/docs", "/redoc"))
    # Outermost: a request under a name the service does not answer to reaches nothing else.
    app.add_middleware(HostCheck, policy=HostPolicy(settings.host, settings.allow_hosts))
    app.add_middleware(TransportHandle)  # before any middleware wraps a websocket's send
    return app
