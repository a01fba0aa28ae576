"""`flockcal record`, `replay` and `convert`: read a Flock of Birds to a raw .fobraw recording, decode one
again (at real time or as fast as possible), and turn one into the .npz take interchange."""

from __future__ import annotations

import signal
import sys
import threading
import time
from pathlib import Path

from flockcal.errors import UserError


def register(subparsers) -> None:
    p = subparsers.add_parser("record", help="read a Flock of Birds and record every byte to a .fobraw file",
                              description="Read a Flock of Birds (device path, pty, socket://, rfc2217:// or sim:// "
                                          "URL) and append every byte, with arrival times, to a .fobraw recording.")
    p.add_argument("--port", action="append", required=True, metavar="URL",
                   help="serial port or pyserial URL; repeat once per bird for one port per bird")
    p.add_argument("-o", "--output", required=True, help="recording to write (.fobraw)")
    p.add_argument("--birds", type=int, default=1, help="number of birds (sensors) in the flock")
    p.add_argument("--rate", type=float, default=None, help="measurement rate in Hz (default: keep the flock's)")
    p.add_argument("--format", default="auto", help="record format: auto, position_matrix, position_quaternion, …")
    p.add_argument("--group", dest="group", action="store_true", default=None, help="force group mode")
    p.add_argument("--per-port", dest="group", action="store_false", help="one port per bird")
    p.add_argument("--hemisphere", default="forward", help="forward, aft, upper, lower, left or right")
    p.add_argument("--scale", type=int, default=None, choices=(36, 72),
                   help="position full scale in inches (default: keep the scale the tracker is set to)")
    p.add_argument("--baud", type=int, default=115200, help="baud rate set by the unit's DIP switches")
    p.add_argument("--mode", default="stream", choices=("stream", "point"))
    p.add_argument("--seconds", type=float, default=None, help="stop after this long (default: until Ctrl-C)")
    p.add_argument("--names", default=None, metavar="A,B,…",
                   help="sensor names, one per bird in address order; kept in the recording for convert and "
                        "replay (default bird1, bird2, …)")
    p.set_defaults(func=_record)

    p = subparsers.add_parser("replay", help="decode a .fobraw recording again",
                              description="Decode a .fobraw recording through the live reader's code path and "
                                          "print what it holds.")
    p.add_argument("recording")
    p.add_argument("--realtime", action="store_true", help="pace the frames by the recorded arrival times")
    p.add_argument("--speed", type=float, default=1.0, help="with --realtime: play this many times faster")
    p.add_argument("--salvage", action="store_true", help="replay what precedes a corrupt chunk")
    p.set_defaults(func=_replay)

    p = subparsers.add_parser("convert", help="convert a .fobraw recording to a .npz take",
                              description="Decode a .fobraw recording and write the .npz take interchange.")
    p.add_argument("recording")
    p.add_argument("-o", "--output", required=True, help="take to write (.npz)")
    p.add_argument("--names", default=None, help="comma-separated sensor names (default: the names the recording "
                   "carries, else bird1, bird2, …)")
    p.add_argument("--salvage", action="store_true", help="convert what precedes a corrupt chunk")
    p.set_defaults(func=_convert)


def parse_names(text: str | None, birds: int, option: str = "--names") -> list[str] | None:
    """Sensor names from a comma-separated option, checked against the number of birds."""
    if text is None:
        return None
    from flockcal.server.settings import NAME_RE

    names = [x.strip() for x in text.split(",")]
    if len(names) != birds:
        raise UserError(f"{option} gives {len(names)} names but there are {birds} birds; give one name per bird")
    bad = [x for x in names if not NAME_RE.fullmatch(x)]
    if bad:
        raise UserError(f"{option}: sensor name {bad[0]!r} is not allowed; use 1–64 letters, digits, space _ . -")
    if len(set(names)) != len(names):
        raise UserError(f"{option}: sensor names must be unique")
    return names


def default_names(m: int) -> list[str]:
    """Names of sensors nobody named: bird1…birdN, as the FBB addresses (and `flockcal serve`) count them."""
    return [f"bird{i + 1}" for i in range(m)]


def _record(args) -> int:
    import logging

    from flockcal.atomic import check_output

    names = parse_names(args.names, args.birds)
    if args.seconds is not None and args.seconds <= 0:
        raise UserError("--seconds must be positive")
    check_output(args.output)  # before the tracker is configured, which takes seconds
    # Events are printed below, once each; the reader's own log would repeat them (shown with -v).
    reader_log = logging.getLogger("flockcal.drivers.reader")
    level = reader_log.level
    if not getattr(args, "verbose", 0):
        reader_log.setLevel(logging.ERROR)
    try:
        return _record_with(args, names)
    finally:
        reader_log.setLevel(level)


def _record_with(args, names: list[str] | None) -> int:
    from flockcal.drivers.rate_check import rate_warning
    from flockcal.drivers.reader import TrackerConfig, TrackerReader
    import flockcal.simulator  # noqa: F401  (registers sim:// with pyserial: --port may be the simulator)

    cfg = TrackerConfig(urls=args.port, birds=args.birds, rate_hz=args.rate, record_format=args.format,
                        group=args.group, hemisphere=args.hemisphere, scale_inches=args.scale, baud=args.baud,
                        mode=args.mode, recording_path=args.output)
    events = []
    span = [None, None, 0]  # first and last frame time, frames

    def on_frames(frames) -> None:
        if span[0] is None:
            span[0] = float(frames.times[0])
        span[1] = float(frames.times[-1])
        span[2] += len(frames)

    def on_event(event) -> None:
        events.append(event)
        started = any(e.kind == "connected" for e in events)
        if event.kind in ("resync", "hemisphere_flip", "stopped", "connected"):
            return
        # Before the first connection a failure is raised and printed once by the command line.
        if started or event.kind not in ("error", "disconnected", "reconnecting", "stalled"):
            print(f"flockcal record: {event}", file=sys.stderr, flush=True)

    reader = TrackerReader(cfg, on_frames=on_frames, on_event=on_event,
                           recording_header={"names": names} if names else None)
    reader.start(wait=60.0)
    setup = reader.setup
    scale = f"{setup.scale_inches:g}-inch scale" + (" (the tracker's own)" if setup.scale_from_tracker else "")
    print(f"flockcal record: {setup.birds} birds on {', '.join(setup.urls)}: {setup.model or 'unknown model'}, "
          f"software {setup.software_revision:.2f}, {scale}, {setup.rate_hz:g} Hz, {setup.record_format} at "
          f"{setup.baud} baud; recording to {args.output} (Ctrl-C stops)", file=sys.stderr, flush=True)
    # SIGTERM (kill, systemd, a supervisor) stops the recording as Ctrl-C does: the file is closed and
    # the "wrote" line printed, instead of the process ending mid-write without a word.
    stop = threading.Event()
    installed = _main_thread()
    previous = signal.signal(signal.SIGTERM, lambda *_: stop.set()) if installed else None
    try:
        end = time.monotonic() + args.seconds if args.seconds else None
        while reader.running and not stop.is_set() and (end is None or time.monotonic() < end):
            stop.wait(0.1)
    except KeyboardInterrupt:
        pass
    finally:
        reader.stop()
        if installed:
            signal.signal(signal.SIGTERM, signal.SIG_DFL if previous is None else previous)
    s = reader.status()
    first, last, n = span
    seconds = (last - first) if n > 1 else 0.0
    got = (n - 1) / seconds if seconds > 0 else 0.0
    print(f"flockcal record: wrote {args.output}: {n} frames of {s.birds} birds in {seconds:.1f} s "
          f"({got:.1f} frames/s; the flock measures at {setup.rate_hz:g} Hz), {setup.record_format}, {scale}; "
          f"{s.dropped_records} bird-frames invalid, {s.resynced} resyncs, {s.reconnects} reconnects",
          file=sys.stderr)
    # Judged over the whole take (the live check looks at its first seconds only), unless it was short.
    warning = rate_warning(setup, got) if seconds >= 1.0 and setup.mode == "stream" else None
    if warning and not any(e.kind == "rate_low" for e in events):
        print(f"flockcal record: warning: {warning}", file=sys.stderr)
    return 0


def _main_thread() -> bool:
    """Signal handlers can only be set from the main thread (tests call the command from others)."""
    return threading.current_thread() is threading.main_thread()


def _decode(rec, replay, **options):
    """`replay(rec)` with a progress bar over its chunks on a terminal (long recordings take a while)."""
    from flockcal.bars import bar

    with bar(len(rec.chunks), "decoding", unit="chunk", unit_scale=True) as shown:
        done = [0]

        def advance(k: int) -> None:
            shown.update(k - done[0])
            done[0] = k

        return replay(rec, on_progress=advance, **options)


def _load(path: str, salvage: bool):
    from flockcal.drivers.recording import read_recording, replay

    rec = read_recording(path, salvage=salvage)
    if rec.truncated:
        print(f"flockcal: {rec.summary()}", file=sys.stderr)
    if not any("stream" in m for m in rec.markers):
        raise UserError(f"{path}: the recording never reached streaming (the flock did not start); nothing to decode")
    return rec, replay


def _replay(args) -> int:
    rec, replay = _load(args.recording, args.salvage)
    if args.speed <= 0:
        raise UserError("--speed must be positive")
    out = _decode(rec, replay, realtime=args.realtime, speed=args.speed)
    if not out.setups:
        raise UserError(f"{args.recording}: the recording never reached streaming ({out.junk.describe()}); nothing "
                        f"to decode")
    if out.junk:
        print(f"flockcal replay: warning: {args.recording}: {out.junk.describe()}", file=sys.stderr)
    f = out.frames
    valid = f.valid.mean() if len(f) else 0.0
    span = f.times[-1] - f.times[0] if len(f) > 1 else 0.0
    setup = out.setups[-1]
    names = rec.settings.get("names")
    print(f"{rec.summary()}")
    print(f"{len(f)} frames of {setup['birds']} birds over {span:.2f} s ({setup['record_format']}, "
          f"{'group mode' if setup['group'] else 'one port per bird'}, {setup['rate_hz']:.1f} Hz); "
          f"{valid:.1%} of bird-frames valid; {out.resyncs} resyncs; {out.sessions} session(s)")
    print(f"sensors: {', '.join(names) if names else 'not named in the recording (convert --names names them)'}")
    for e in out.events:
        if e.get("event") not in ("resync", "hemisphere_flip"):
            print(f"  {e['event']}: {e.get('message', '')}")
    if len(f):
        from flockcal.hemisphere_unfold import unfold_positions

        _, how = unfold_positions(f.times, f.positions, f.valid, setup.get("hemisphere"))
        print(how.summary(names or default_names(f.valid.shape[1])) or "no hemisphere flips left to unfold")
    return 0


def _convert(args) -> int:
    from flockcal.atomic import check_output
    from flockcal.commands.takecheck import PARTIAL_EXIT

    check_output(args.output)
    take, out = convert_recording(args.recording, args.output, names=args.names, salvage=args.salvage,
                                  command="convert")
    print(f"wrote {args.output}: {take.n_frames} frames of {len(take.names)} sensors ({', '.join(take.names)}), "
          f"{take.valid_fraction:.1%} valid", file=sys.stderr)
    if out.junk:
        print(f"flockcal convert: warning: {args.recording}: {out.junk.describe()}; the take holds what the rest "
              f"decoded to (exit status {PARTIAL_EXIT})", file=sys.stderr)
        return PARTIAL_EXIT
    return 0


def convert_recording(path: str, output: str, names: str | None = None, salvage: bool = False,
                      command: str | None = None):
    """Decode the .fobraw at `path` into the take `output` a chunk at a time (what `flockcal convert` does):
    decoded as the live reader decodes it, the hemisphere flips the reader could not undo undone as `fit`
    undoes them (`command`, when given, says on stderr how many frames that unfolded), written as it comes.
    Memory stays a read block and a batch of frames whatever the recording's length, and nothing is left at
    `output` when it fails. (the TakeWriter, for its counts; the Replay, without frames, for its junk)."""
    from flockcal.bars import bar
    from flockcal.drivers.recording import ChunkReader, Decoder, RecordingError, decode_recording
    from flockcal.hemisphere_unfold import HemisphereUnfold
    from flockcal.take_files import TakeWriter

    reader = ChunkReader(path, salvage)
    made: list[TakeWriter] = []

    def on_frames(f) -> None:
        setup = dec.setups[-1]
        if not made:
            given = take_names(path, names, reader.settings, f.n_sensors)
            unfold = HemisphereUnfold(len(given), setup.get("hemisphere"))
            made.append(TakeWriter(output, given, setup["rate_hz"], source=path, unfold=unfold))
        check_carried(path, f, setup)
        made[0].append(f)

    dec = Decoder(reader.settings, on_frames, keep=False)
    try:
        with bar(reader.size, "decoding", unit="B", unit_scale=True) as shown:
            done = [0]

            def advance(at: int) -> None:
                shown.update(at - done[0])
                done[0] = at

            out = decode_recording(reader, dec, on_progress=advance)
        if reader.problem:
            print(f"flockcal: {Path(path).name}: recovered {reader.good_bytes} of {reader.size} bytes "
                  f"({reader.problem})", file=sys.stderr)
        if not out.setups:
            junk = f" ({out.junk.describe()})" if out.junk else ""
            raise UserError(f"{path}: the recording never reached streaming (the flock did not start){junk}; "
                            f"nothing to decode")
        if not made:
            raise RecordingError(f"{path}: no complete frame could be decoded")
        writer = made[0]
        writer.rate_hz = out.setups[-1]["rate_hz"]
        writer.commit()
        note = writer.unfold.summary(writer.names)
        if note and command is not None:
            print(f"flockcal {command}: {path}: {note}", file=sys.stderr)
        return writer, out
    except BaseException:
        if made:
            made[0].discard()
        raise


def recording_take(path: str, names: str | None = None, salvage: bool = False, command: str | None = None):
    """The `Take` `flockcal convert` writes for a .fobraw recording, in memory (`flockcal batch` fits it the
    same way): decoded as the live reader decodes it, then the hemisphere flips the reader could not undo
    (sensors outside the hemisphere from the start, or a recording made without tracking it) undone as `fit`
    undoes them; `command`, when given, says on stderr how many frames that unfolded."""
    from flockcal.commands.outputs import unfolded
    from flockcal.drivers.recording import RecordingError
    from flockcal.hemisphere_unfold import unfold_take
    from flockcal.takes import make_take

    rec, replay = _load(path, salvage)
    out = _decode(rec, replay)
    f = out.frames
    if not out.setups or len(f) == 0:
        raise RecordingError(f"{path}: no complete frame could be decoded")
    setup = out.setups[-1]
    names = take_names(path, names, rec.settings, f.valid.shape[1])
    check_carried(path, f, setup)
    take = make_take(f.rotations, f.positions, names, setup["rate_hz"], valid=f.valid, times=f.times - f.times[0],
                     source=path)
    if command is None:
        return unfold_take(take, setup.get("hemisphere"))[0]
    return unfolded(take, command, path, setup.get("hemisphere"))


def take_names(path: str, names: str | None, settings: dict, m: int) -> list[str]:
    """The sensor names of a recording's take: --names, else the names its header carries, else bird1…birdN."""
    from flockcal.drivers.recording import RecordingError

    given = parse_names(names, m) or settings.get("names") or default_names(m)
    if len(given) != m:
        raise RecordingError(f"{path}: its header names {len(given)} sensors but it holds {m} birds; "
                             f"name them with --names")
    return given


def check_carried(path: str, f, setup: dict) -> None:
    """RecordingError when valid frames lack position or orientation (a record format a take cannot hold)."""
    import numpy as np

    from flockcal.drivers.recording import RecordingError

    carried = np.isfinite(f.positions).all(axis=2) & np.isfinite(f.rotations).all(axis=(2, 3))
    if (f.valid & ~carried).any():
        raise RecordingError(f"{path}: its record format {setup['record_format']} lacks position or "
                             f"orientation; a take needs both (record with position_matrix or position_quaternion)")
