"""`flockcal simulate`: write a simulated take (.npz plus its ground truth), an optical marker take (C3D or
the marker .npz), a folder of one performer's takes, or serve a fake Flock of Birds on a pseudo-terminal
that any serial client can open.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

from flockcal.errors import UserError

_SLIP = re.compile(r"^(?P<sensor>[A-Za-z_][\w]*)@(?P<time>[0-9.]+):(?P<mm>[0-9.]+)(?::(?P<deg>-?[0-9.]+))?$")


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "simulate",
        help="simulate a performer: write a take .npz with its truth, or serve a fake tracker on a pty",
        description="Simulate a performer wearing Flock of Birds sensors. Writes the .npz take "
        "interchange and <stem>.truth.json beside it; with --markers (or -o ending in .c3d) an optical marker "
        "take instead; with --archive a folder of one performer's takes; with --pty serves a fake tracker.",
    )
    p.add_argument("--model", default="human", choices=["human", "linkage", "pair"],
                   help="body: human (2–16 sensors), linkage (the paper's 6-link chain), pair (two sensors "
                   "0.565 m apart, for the unit scale)")  # fmt: skip
    p.add_argument("--motion", default="walk", choices=["exercise", "walk", "kiosk", "idle"], help="routine (default walk)")
    p.add_argument("--seconds", type=float, default=45.0, help="length of the take (default 45)")
    p.add_argument("--rate", type=float, default=100.0, metavar="HZ", help="frames per second, 1–144 (default 100)")
    p.add_argument("--birds", type=int, help="sensors to use (human default 16; fewer keeps a connected subset)")
    p.add_argument("--seed", type=int, default=1, help="seed for the subject, the motion and the noise (default 1)")
    p.add_argument("--height", type=float, default=1.75, help="the human's height in metres (default 1.75)")
    p.add_argument("--noise", default="tracker", choices=["tracker", "none"], help="tracker noise or exact poses")
    p.add_argument("--sta-mm", type=float, metavar="MM",
                   help="soft-tissue artefact: how far a skin sensor slides as a neighbouring joint reaches the "
                   "end of its range (human default 12, 0 = off; the linkage and pair have none)")
    p.add_argument("--dropout", type=float, default=0.0, metavar="P", help="probability a sensor-frame is lost")
    p.add_argument("--slip", action="append", default=[], metavar="SENSOR@T:MM[:DEG]",
                   help="a sensor slides MM millimetres (and turns DEG degrees) at T seconds; repeatable")  # fmt: skip
    p.add_argument("--unit-scale", type=float, default=1.0, help="tracker unit-scale error, e.g. 1.02")
    p.add_argument("--quantise", type=float, choices=[36.0, 72.0, 144.0], metavar="INCHES",
                   help="round to the Flock's 14-bit words at this full scale (36, 72 or 144)")
    p.add_argument("--hemisphere", choices=["forward", "aft", "left", "right", "upper", "lower"],
                   help="mirror sensors outside this hemisphere, as the Flock does")
    p.add_argument("-o", "--output", type=Path,
                   help="take file (default take.npz; with --markers take.c3d)")
    p.add_argument("--pty", action="store_true",
                   help="instead of writing a take, serve a fake Flock of Birds on a pty and print its path")
    m = p.add_argument_group("optical markers (--markers)")
    m.add_argument("--markers", action="store_true",
                   help="write an optical marker take instead: skin markers seen by cameras, as .c3d (needs pip "
                        "install 'flockcal[optical]') or the marker .npz, by -o's extension; a .c3d -o implies it")
    m.add_argument("--markers-per-body", default="3-4", metavar="N[-M]",
                   help="markers on each body, or a range drawn per body (default 3-4)")
    m.add_argument("--marker-noise-mm", type=float, default=1.0, metavar="MM",
                   help="camera noise per coordinate (default 1; --noise none: 0)")
    m.add_argument("--occlusion", type=float, default=0.0, metavar="F",
                   help="fraction of each marker's frames hidden, in gaps of about 0.25 s (default 0)")
    m.add_argument("--swaps", type=int, default=0, metavar="N", help="label swaps between markers of different bodies")
    a = p.add_argument_group("archive (--archive)")
    a.add_argument("--archive", type=Path, metavar="DIR",
                   help="write a folder of takes instead: one performer's session cut into --takes takes of "
                        "--seconds each (take01.npz …, each with its truth), the input `flockcal batch` reads")
    a.add_argument("--takes", type=int, default=6, metavar="N", help="takes in the --archive (default 6)")
    p.set_defaults(func=run)


def _slips(specs: list[str]) -> list[dict]:
    out = []
    for spec in specs:
        m = _SLIP.match(spec)
        if not m:
            raise UserError(f"--slip {spec!r}: write SENSOR@SECONDS:MILLIMETRES[:DEGREES], e.g. l_forearm@20:20")
        out.append(
            {
                "sensor": m["sensor"],
                "at_time": float(m["time"]),
                "distance_m": float(m["mm"]) / 1000.0,
                "angle_deg": float(m["deg"] or 0.0),
            }
        )
    return out


PTY_BAUD = 115200  # the fake's line runs at the RS-232 top speed, as a Flock's DIP switches allow


def record_command(device: str, names, rate_hz: float) -> str:
    """A `flockcal record` line for the fake: its sensor names, and the highest whole rate up to the
    fake's own that one 115200-baud line carries for the whole flock (group mode, position/quaternion)."""
    from flockcal.drivers.records import record_length
    from flockcal.drivers.link import LINK_MARGIN, link_capacity

    per_set = len(names) * record_length("position_quaternion", group=len(names) > 1)
    fits = int(link_capacity(PTY_BAUD) * LINK_MARGIN // per_set)
    rate = f" --rate {fits}" if fits < rate_hz else ""
    return (f"flockcal record --port {device} --birds {len(names)}{rate} --names {','.join(names)} "
            f"-o recorded.fobraw")


def truth_path(take_path: Path) -> Path:
    """Where the truth of `take.npz` goes: `take.truth.json` beside it."""
    return take_path.with_name(take_path.stem + ".truth.json")


# What each mode cannot take: the options that belong to another (`None`: left at its default).
TRACKER_FAULTS = ("dropout", "slip", "unit_scale", "quantise", "hemisphere")
MARKER_OPTIONS = ("markers_per_body", "marker_noise_mm", "occlusion", "swaps")


def run(args: argparse.Namespace) -> int:
    from flockcal.simulator.body import SimulatorError

    markers = args.markers or (args.output is not None and args.output.suffix.lower() == ".c3d")
    modes = [name for name, on in (("--pty", args.pty), ("--markers", markers), ("--archive", args.archive)) if on]
    if len(modes) > 1:
        raise UserError(f"{' and '.join(modes)} are different things to make; give one of them")
    refuse(args, TRACKER_FAULTS if markers else (), "a tracker fault; a marker take has --occlusion, --swaps "
                                                    "and --marker-noise-mm" if markers else "")
    refuse(args, () if markers else MARKER_OPTIONS, "for a marker take (--markers)")
    if args.archive is not None and args.output is not None:
        raise UserError("--archive names the folder to write; -o is for one take")
    if args.takes != 6 and args.archive is None:
        raise UserError("--takes is the number of takes in an --archive; give --archive DIR too")
    try:
        if args.pty:
            return _serve_pty(args)
        if markers:
            return _write_markers(args)
        if args.archive is not None:
            return _write_archive(args)
        return _write_take(args)
    except SimulatorError as exc:
        raise UserError(str(exc)) from None


def refuse(args: argparse.Namespace, options, why: str) -> None:
    """UserError naming the first of `options` (dest names) given a value other than its default."""
    defaults = {"dropout": 0.0, "slip": [], "unit_scale": 1.0, "quantise": None, "hemisphere": None,
                "markers_per_body": "3-4", "marker_noise_mm": 1.0, "occlusion": 0.0, "swaps": 0}
    for dest in options:
        if getattr(args, dest) != defaults[dest]:
            raise UserError(f"--{dest.replace('_', '-')} is {why}")


def _faults(args: argparse.Namespace) -> dict:
    """The tracker faults the options ask for, as `simulator.take.simulate` takes them."""
    faults: dict = {}
    if args.dropout:
        faults["dropout"] = args.dropout
    if args.slip:
        faults["slips"] = _slips(args.slip)
    if args.unit_scale != 1.0:
        faults["unit_scale"] = args.unit_scale
    if args.quantise:
        faults["quantise"] = args.quantise
    if args.hemisphere:
        faults["hemisphere"] = args.hemisphere
    return faults


def _birds(args: argparse.Namespace) -> int | None:
    return args.birds if args.birds is not None else (16 if args.model == "human" else None)


def _write_take(args: argparse.Namespace) -> int:
    from flockcal.simulator.take import simulate
    from flockcal.atomic import check_output, write_atomic
    from flockcal.takes import save_take

    faults = _faults(args)
    out: Path = args.output or Path("take.npz")
    if out.suffix != ".npz":
        raise UserError(f"{out}: the take is written as .npz (a marker take as .c3d); give a name ending in .npz")
    check_output(out)
    birds = _birds(args)
    from flockcal.bars import Stages

    tp = truth_path(out)
    with Stages("simulate", ["simulating", "writing"]) as stages:
        stages.step("simulating")
        take, truth = simulate(
            model=args.model, motion=args.motion, seconds=args.seconds, rate_hz=args.rate, birds=birds,
            seed=args.seed, noise=None if args.noise == "none" else "tracker", faults=faults, height=args.height,
            sta_mm=args.sta_mm,
        )  # fmt: skip
        stages.step("writing")
        save_take(out, take)
        write_atomic(tp, json.dumps(truth, indent=1) + "\n")
    sta = truth["simulation"]["sta_mm"]
    skin = f", soft tissue {sta:g} mm" if sta else ""
    print(f"wrote {out} ({take.n_frames} frames × {take.n_sensors} sensors, {args.motion}, {args.seconds:g} s{skin}) "
          f"and {tp}", file=sys.stderr)
    return 0


def _per_body(text: str) -> tuple[int, int]:
    """--markers-per-body N or N-M as (low, high); UserError unless 1 <= low <= high <= 12."""
    parts = text.split("-")
    try:
        low, high = int(parts[0]), int(parts[-1])
    except ValueError:
        low = high = -1
    if len(parts) > 2 or not 1 <= low <= high <= 12:
        raise UserError(f"--markers-per-body {text!r}: give a count or a range from 1 to 12, e.g. 3 or 3-4")
    return low, high


def _write_markers(args: argparse.Namespace) -> int:
    """An optical marker take from the simulator's optical model (`simulator.optical.simulate_markers`)."""
    from flockcal.atomic import check_output, write_atomic
    from flockcal.bars import Stages
    from flockcal.markers import ezc3d_module, save_markers

    out: Path = args.output or Path("take.c3d")
    if out.suffix.lower() not in (".c3d", ".npz"):
        raise UserError(f"{out}: a marker take is written as .c3d or as the marker .npz; give a name ending in one")
    per_body = _per_body(args.markers_per_body)
    if not 0 <= args.occlusion < 1:
        raise UserError(f"--occlusion must be a fraction from 0 to below 1, got {args.occlusion}")
    if not 0 <= args.marker_noise_mm <= 100 or args.swaps < 0:
        raise UserError("--marker-noise-mm must be 0 to 100 and --swaps 0 or more")
    check_output(out)
    if out.suffix.lower() == ".c3d":
        ezc3d_module("writing")  # the one-line error before any work, not after it
    from flockcal.simulator.body import by_name
    from flockcal.simulator.optical import simulate_markers

    tp = truth_path(out)
    with Stages("simulate", ["simulating", "writing"]) as stages:
        stages.step("simulating")
        model = by_name(args.model, seed=args.seed, birds=_birds(args), height=args.height)
        take, truth = simulate_markers(
            model, args.motion, seconds=args.seconds, rate_hz=args.rate, seed=args.seed, per_body=per_body,
            noise_m=0.0 if args.noise == "none" else args.marker_noise_mm / 1000.0, occlusion=args.occlusion,
            n_swaps=args.swaps, sta_mm=args.sta_mm or 0.0,
        )  # fmt: skip
        truth["simulation"] = {"model": model.kind, "motion": args.motion, "seconds": float(args.seconds),
                               "rate_hz": float(args.rate), "frames": take.n_frames, "seed": int(args.seed),
                               "markers_per_body": list(per_body), "marker_noise_mm": args.marker_noise_mm,
                               "occlusion": args.occlusion, "swaps": args.swaps}
        stages.step("writing")
        save_markers(out, take)
        write_atomic(tp, json.dumps(truth, indent=1) + "\n")
    print(f"wrote {out} ({take.n_frames} frames × {take.n_markers} markers on {model.m} bodies, {args.motion}, "
          f"{args.seconds:g} s) and {tp}", file=sys.stderr)
    return 0


def _write_archive(args: argparse.Namespace) -> int:
    """One performer's session as a folder of takes (`simulator.take.simulate_session`)."""
    from flockcal.atomic import write_atomic
    from flockcal.bars import Stages
    from flockcal.simulator.take import simulate_session
    from flockcal.takes import save_take

    folder: Path = args.archive
    if args.takes < 1:
        raise UserError(f"--takes must be 1 or more, got {args.takes}")
    names = [f"take{k:0{max(2, len(str(args.takes)))}d}.npz" for k in range(1, args.takes + 1)]
    if folder.exists() and not folder.is_dir():
        raise UserError(f"--archive {folder}: that is a file; give a folder (it is made if it does not exist)")
    if folder.is_dir():
        # A take left from another run would join the batch (and --combine) unasked: refuse, naming it.
        other = sorted(x.name for x in folder.iterdir() if x.suffix.lower() in (".npz", ".fobraw", ".c3d")
                       and x.name not in names)
        if other:
            raise UserError(f"--archive {folder}: the folder holds other takes ({', '.join(other[:3])}"
                            f"{', …' if len(other) > 3 else ''}); give an empty or new folder")
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"--archive {folder}: cannot make the folder ({exc.strerror})") from None
    session = simulate_session(
        args.takes, model=args.model, motion=args.motion, seconds=args.seconds, rate_hz=args.rate,
        birds=_birds(args), seed=args.seed, noise=None if args.noise == "none" else "tracker", faults=_faults(args),
        height=args.height, sta_mm=args.sta_mm,
    )  # fmt: skip
    with Stages("simulate", names) as stages:
        for name, (take, truth) in zip(names, session):
            stages.step(name)
            save_take(folder / name, take)
            write_atomic(truth_path(folder / name), json.dumps(truth, indent=1) + "\n")
    sta = truth["simulation"]["sta_mm"]
    print(f"wrote {folder}/: {args.takes} takes of {args.seconds:g} s ({take.n_frames} frames × {take.n_sensors} "
          f"sensors) by one performer ({args.model}, seed {args.seed}, {args.motion}"
          f"{f', soft tissue {sta:g} mm' if sta else ''}), each with its truth", file=sys.stderr)
    return 0


def _serve_pty(args: argparse.Namespace) -> int:
    import signal
    import threading

    from flockcal.simulator.performer import Performer

    from flockcal.simulator.pty_tracker import PtyTracker
    birds = _birds(args)
    source = Performer(args.model, routine=args.motion, seed=args.seed, rate_hz=args.rate, birds=birds,
                       noise=None if args.noise == "none" else "tracker", height=args.height,
                       sta_mm=args.sta_mm)  # fmt: skip
    if args.dropout:
        source.set_dropout(args.dropout)
    if args.unit_scale != 1.0:
        source.set_unit_scale(args.unit_scale)
    for s in _slips(args.slip):
        source.inject_slip(s["sensor"], s["distance_m"], at_time=s["at_time"], angle_deg=s["angle_deg"])
    # Ctrl-C and SIGTERM only set an event the main loop waits on: a KeyboardInterrupt raised wherever the
    # main thread happens to be (under load, in a print or in interpreter shutdown) left the process dying
    # of SIGINT, or hanging, instead of stopping the tracker and exiting 0 (tests/test_simulator_cli.py).
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    tracker = PtyTracker(source, birds=source.n_sensors, rate_hz=args.rate, scale_inches=source.full_scale_in,
                         baud=PTY_BAUD)
    tracker.start()
    try:
        print(tracker.device, flush=True)
        print(
            f"fake Flock of Birds: {source.n_sensors} birds ({', '.join(source.names)}), {args.motion}, "
            f"{args.rate:g} Hz, {source.full_scale_in:g}-inch scale, {PTY_BAUD} baud; Ctrl-C to stop",
            file=sys.stderr,
            flush=True,
        )
        print(f"record it with: {record_command(tracker.device, source.names, args.rate)}", file=sys.stderr, flush=True)
        while not stop.wait(0.5):
            pass
    finally:
        tracker.stop()
    return 0
