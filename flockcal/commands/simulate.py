"""`flockcal simulate`: write a simulated take (.npz plus its ground truth), or serve a fake Flock of
Birds on a pseudo-terminal that any serial client can open.
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
        "interchange and <stem>.truth.json beside it, or with --pty serves a fake tracker.",
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
    p.add_argument("-o", "--output", type=Path, default=Path("take.npz"), help="take file (default take.npz)")
    p.add_argument("--pty", action="store_true",
                   help="instead of writing a take, serve a fake Flock of Birds on a pty and print its path")
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


def run(args: argparse.Namespace) -> int:
    from flockcal.simulator.body import SimulatorError

    try:
        if args.pty:
            return _serve_pty(args)
        return _write_take(args)
    except SimulatorError as exc:
        raise UserError(str(exc)) from None


def _write_take(args: argparse.Namespace) -> int:
    from flockcal.simulator.take import simulate
    from flockcal.atomic import check_output, write_atomic
    from flockcal.takes import save_take

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
    out: Path = args.output
    if out.suffix != ".npz":
        raise UserError(f"{out}: the take is written as .npz; give a name ending in .npz")
    check_output(out)
    birds = args.birds if args.birds is not None else (16 if args.model == "human" else None)
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


def _serve_pty(args: argparse.Namespace) -> int:
    import signal
    import threading

    from flockcal.simulator.performer import Performer

    from flockcal.simulator.pty_tracker import PtyTracker
    birds = args.birds if args.birds is not None else (16 if args.model == "human" else None)
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
