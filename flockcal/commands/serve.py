"""`flockcal serve`: the live calibration service (REST API, websocket, dashboard) under uvicorn.

With no --device it runs the built-in simulator, so it works on a machine with no tracker attached.
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
from pathlib import Path

from flockcal.errors import UserError
from flockcal.commands.fit import add_tolerance


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "serve",
        help="run the live calibration service (dashboard, REST API, websocket)",
        description="Run the live calibration service: reads the tracker, fits the skeleton live, "
                    "serves a dashboard at / and the API at /api (docs at /docs).",
    )
    p.add_argument("--device", metavar="URL", help="tracker pyserial URL or device path "
                   "(/dev/ttyUSB0, socket://host:port, rfc2217://…); default: the built-in simulator")
    p.add_argument("--birds", type=int, default=16, help="number of sensors (default 16)")
    p.add_argument("--rate", type=float, metavar="HZ", help="measurement rate to ask the tracker for")
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1; "
                   "any other address needs --token)")
    p.add_argument("--http-port", type=int, default=8750, help="HTTP port (default 8750)")
    p.add_argument("--data-dir", type=Path, help="sessions database and recordings "
                   "(default $XDG_DATA_HOME/flockcal or ~/.local/share/flockcal)")
    p.add_argument("--token", help="admin token: every mutating request needs 'Authorization: Bearer TOKEN' "
                   "(also read from $FLOCKCAL_TOKEN)")
    p.add_argument("--read-token", help="read-only token for dashboards (GET and the websocket)")
    p.add_argument("--kiosk-token", help="token that can read and start/stop sessions, nothing else")
    p.add_argument("--names", help="comma-separated sensor names, one per bird (default: the simulator's "
                   "body names for sim://, else bird1..birdN)")
    p.add_argument("--scale", type=int, choices=(36, 72), help="position full scale in inches "
                   "(default 72 for the simulator, else the scale the tracker is set to)")
    p.add_argument("--baud", type=int, metavar="BAUD", help="serial line speed (default 115200, or the baud= of "
                   "a sim:// URL); the driver picks a record format the line can carry")
    p.add_argument("--fit-hz", type=float, default=30.0, help="full refits per second (default 30)")
    add_tolerance(p)
    p.add_argument("--target-mm", type=float, metavar="MM",
                   help="a joint counts as calibrated (progress, done, the kiosk ring) once the data pin its centre "
                        "to within MM along every direction it needs (default: --tolerance-mm / 1.414, so bones "
                        "between two such joints are within the tolerance)")
    p.add_argument("--profile", choices=("stage", "kiosk"), default="stage",
                   help="how a session decides it is calibrated when its start does not say (the kiosk page "
                        "always asks for kiosk): stage = pinned to --target-mm (default); kiosk = pinned to "
                        "10 mm and no longer changed by more data, what a guest's avatar needs (docs/service.md)")
    p.add_argument("--fast-init", action="store_true", default=bool(os.environ.get("FLOCKCAL_FAST_INIT")),
                   help="skip the tracker's reset delays (for simulated trackers on a pty)")
    p.add_argument("--skeleton", action="append", default=[], type=Path, metavar="FILE",
                   help="a performer's skeleton file (from `flockcal skeleton` or a session's download), "
                        "offered as a session preset: topology and bones kept, only sensor placements fitted "
                        "(repeatable)")
    p.add_argument("--keep-days", type=float, metavar="DAYS",
                   help="retention: keep the frames and raw recordings of the last DAYS days; older sessions keep "
                        "their result, skeleton file and events (default: keep everything; docs/kiosk.md)")
    p.add_argument("--keep-disk", type=float, metavar="GB",
                   help="retention: prune the oldest sessions' frames and raw recordings while the data directory "
                        "is over GB gigabytes (pinned sessions are never pruned)")
    p.add_argument("--cors-origin", action="append", default=[], metavar="ORIGIN",
                   help="allow browser pages from this origin (repeatable; CORS is closed by default)")
    p.add_argument("--allow-host", action="append", default=[], metavar="NAME",
                   help="a host name (or address) the service is reached by, besides loopback's and --host's; "
                        "requests naming any other Host are refused (DNS rebinding; repeatable)")
    p.add_argument("--max-session-min", type=float, default=120.0, metavar="MIN",
                   help="stop a live session (result stored, an event saying why) once it has recorded this long "
                        "(default 120; 0: no maximum)")
    p.add_argument("--min-free-mb", type=float, default=500.0, metavar="MB",
                   help="stop recording cleanly before the data directory's disk has less than MB free, and "
                        "refuse new sessions below it (default 500)")
    p.add_argument("--request-deadline-s", type=float, default=10.0, metavar="S",
                   help="a request must arrive whole within S seconds of its first byte, or its connection is "
                        "closed (default 10)")
    p.add_argument("--download-stall-s", type=float, default=30.0, metavar="S",
                   help="a download whose client takes no data for S seconds is cut off and its slot freed "
                        "(default 30)")
    p.add_argument("--vrpn", type=int, nargs="?", const=3883, metavar="PORT",
                   help="serve the live humanoid as the VRPN tracker flockcal@HOST:PORT, one sensor per bone "
                        "(TCP and UDP; PORT default 3883, VRPN's; docs/outputs.md)")
    p.add_argument("--osc", action="append", default=[], metavar="HOST[:PORT]",
                   help="send the live humanoid over the VMC protocol (OSC/UDP) to this receiver (PORT default "
                        "39539; repeatable, or several separated by commas)")
    p.add_argument("--osc-hz", type=float, default=60.0, metavar="HZ",
                   help="VMC frames a second (default 60)")
    p.set_defaults(func=run)


def settings_from_args(args: argparse.Namespace):
    from flockcal.commands.fit import tolerance_m

    from flockcal.server.settings import Settings, default_data_dir

    names = tuple(x.strip() for x in args.names.split(",")) if args.names else None
    return Settings(
        device=args.device,
        birds=args.birds,
        rate_hz=args.rate,
        host=args.host,
        http_port=args.http_port,
        data_dir=args.data_dir or default_data_dir(),
        token=_token(args.token, "FLOCKCAL_TOKEN"),
        read_token=_token(args.read_token, "FLOCKCAL_READ_TOKEN"),
        kiosk_token=_token(args.kiosk_token, "FLOCKCAL_KIOSK_TOKEN"),
        names=names,
        fit_hz=args.fit_hz,
        tolerance_m=tolerance_m(args),
        target_m=None if args.target_mm is None else float(args.target_mm) / 1000.0,
        profile=args.profile,
        cors_origins=tuple(args.cors_origin),
        allow_hosts=tuple(args.allow_host),
        max_session_s=args.max_session_min * 60.0 if args.max_session_min else None,
        min_free_bytes=int(args.min_free_mb * 2**20),
        request_deadline_s=args.request_deadline_s,
        download_stall_s=args.download_stall_s,
        fast_init=args.fast_init,
        scale_inches=args.scale,
        baud=args.baud,
        skeletons=tuple(args.skeleton),
        keep_days=args.keep_days,
        keep_disk_gb=args.keep_disk,
        vrpn_port=args.vrpn,
        osc_targets=tuple(args.osc),
        osc_hz=args.osc_hz,
    )


class DamagedDatabase(UserError):
    """The data directory's database is damaged: an exit status of its own, which the kiosk unit's
    RestartPreventExitStatus keeps systemd from restarting into the same failure every 5 s."""

    exit_code = 4


def _token(option: str | None, variable: str) -> str | None:
    """The option as given (a blank one is refused by Settings.check, not read as "no token"), else the
    environment variable unless it is empty."""
    if option is not None:
        return option
    return os.environ.get(variable) or None


def websocket_library() -> str:
    """The websocket implementation uvicorn will use; UserError when none is installed (uvicorn alone
    answers /ws/live with 404, and the dashboard and kiosk wait for a live feed forever)."""
    import importlib.util

    for name in ("websockets", "wsproto"):
        if importlib.util.find_spec(name) is not None:
            return name
    raise UserError("no websocket library is installed, so /ws/live could not stream to the dashboard and kiosk; "
                    "install one with `pip install websockets` (a dependency of flockcal: reinstall flockcal)")


def stop_report(service) -> list[str]:
    """What a stopped service kept, one line each: the session it closed (and where its files are), or
    that no session was live."""
    data = service.data_dir
    row = service.stopped_session
    lines = []
    if row is None:
        lines.append("no session was live; nothing new to save")
    else:
        kept = "result stored" if row.has_result else (row.note or "no result")
        lines.append(f"stopped session {row.id} ({row.performer or '?'}, {row.frames} frames): {kept}")
        rec = service.sessions
        for path in (rec.frames_path(row.id), rec.raw_path(row.id)):
            if path.exists():
                lines.append(f"saved {path}")
    lines.append(f"sessions, results and events in {data / 'flockcal.sqlite3'}")
    return lines


def settle_heap() -> None:
    """Ready the process for serving: load what the live pose loads on its first use, then freeze what start-up
    made (modules, the app, the service's parts) out of the collector's sight.

    Both would otherwise stall every thread: the pose's first skeleton imports the rig's naming (scipy's
    spatial package: 0.2-0.6 s on the event loop, every client's messages waiting), and a full collection
    walks every object the process holds while holding the GIL (45-90 ms with the start-up's objects in
    it, the slowest step of a live session; frozen, a full collection walks only what serving made since).
    """
    import gc

    import flockcal.exports.bvh  # noqa: F401  (server/pose.py imports it where it names the rig's nodes)

    gc.collect()
    gc.freeze()


def run(args: argparse.Namespace) -> int:
    import uvicorn

    from flockcal.clock import SYSTEM
    from flockcal.server.app import create_app
    from flockcal.server.connections import ConnectionGuard, connection_cap, guarded_protocol, raise_fd_limit
    from flockcal.server.errors import ConfigError
    from flockcal.server.logthrottle import throttle_all_handlers
    from flockcal.server.wsprotocol import websocket_protocol
    from flockcal.server.listen import listen_socket

    websocket_library()
    # Descriptors: a unit with no LimitNOFILE gives 1024; take what the hard limit allows.
    soft, _hard = raise_fd_limit()
    try:
        settings = settings_from_args(args).check()
    except ConfigError as exc:
        raise UserError(str(exc)) from None
    try:
        settings.data_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"cannot create the data directory {settings.data_dir}: {exc.strerror}; pick another with --data-dir") from None
    from flockcal.errors import FlockcalError
    from flockcal.server.errors import DatabaseDamaged
    from flockcal.server.service import Service

    try:
        sock = listen_socket(settings.host, settings.http_port, settings.send_buffer_bytes)
    except OSError as exc:
        raise UserError(f"cannot listen on {settings.host}:{settings.http_port}: {exc.strerror}; "
                        "choose another --http-port or --host") from None
    try:
        service = Service(settings, clock=SYSTEM)  # opens (and checks) the database and the device before serving
    except DatabaseDamaged as exc:
        sock.close()
        raise DamagedDatabase(str(exc)) from None
    except FlockcalError as exc:
        sock.close()
        raise UserError(str(exc)) from None
    except OSError as exc:  # the data directory's recordings or skeletons folder on a full or read-only disk
        sock.close()
        where = exc.filename or settings.data_dir
        raise UserError(f"cannot write {where}: {exc.strerror}; make room on that disk or give another --data-dir") from None
    if settings.http_port == 0:  # the port the system picked is the one to print
        settings = settings.with_(http_port=sock.getsockname()[1])
    app = create_app(settings, service)
    host = f"[{settings.host}]" if ":" in settings.host else settings.host
    log = logging.getLogger("flockcal.serve")
    logging.getLogger("flockcal").setLevel(logging.INFO)
    base = f"http://{host}:{settings.http_port}"
    print(f"flockcal serve: tracker {settings.device_url}", flush=True)
    print(f"flockcal serve: dashboard {base}/   kiosk {base}/kiosk   API docs {base}/docs", flush=True)
    print(f"flockcal serve: data in {settings.data_dir}", flush=True)
    print(f"flockcal serve: retention: {service.retention.policy.describe()}", flush=True)
    for line in service.outputs.lines if service.outputs is not None else ():
        print(f"flockcal serve: {line}", flush=True)
    for entry in service.skeletons.list():
        print(f"flockcal serve: skeleton preset {entry['name']!r} ({entry['origin']})", flush=True)
    log.info("listening on %s", base)
    # No per-message deflate: compressing every snapshot once per client costs more CPU than the
    # loopback or LAN bandwidth it saves.
    # Every request whole within a deadline, connections capped under the descriptors (server/connections.py).
    guard = ConnectionGuard(connection_cap(soft), service.clock, settings.request_deadline_s)
    app.state.connection_guard = guard
    config = uvicorn.Config(app, host=settings.host, port=settings.http_port, log_level="warning",
                            ws_max_size=64 * 1024, ws_per_message_deflate=False, lifespan="on",
                            http=guarded_protocol(guard), ws=websocket_protocol(),
                            # A stop waits this long for responses in flight (a download), then cuts them:
                            # systemd's TimeoutStopSec (30 s) must not run out first.
                            timeout_graceful_shutdown=10)
    throttle_all_handlers(service.clock)  # after uvicorn.Config: it configures uvicorn's handlers
    server = uvicorn.Server(config)
    settle_heap()
    # uvicorn stops gracefully on SIGTERM as on Ctrl-C, then raises the signal again with the handler it
    # found: Python's default for SIGTERM ends the process there, before the stop report below. With a
    # handler of ours that re-raised signal only ends `run`, so `systemctl stop` prints what Ctrl-C prints.
    previous = signal.signal(signal.SIGTERM, lambda *_: None)
    try:
        server.run(sockets=[sock])
    finally:
        signal.signal(signal.SIGTERM, previous)
        for line in stop_report(service):
            print(f"flockcal serve: {line}", flush=True)
    return 0
