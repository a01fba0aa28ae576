"""Sub-commands for what people take away from a calibration: `scale` (tracker unit scale from a rigid
pair), `report` (one HTML page), `export-bvh` (animation for Blender/Maya/MotionBuilder), `export-gltf`
(a glTF 2.0 rig for engines and viewers) and `skeleton` (the performer's skeleton file, for their next take).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from flockcal.commands.takecheck import PARTIAL_EXIT
from flockcal.errors import UserError


def scale_factor(text: str) -> float:
    """A `--scale` value: a number, or a JSON file written by `flockcal scale --json` (its "factor")."""
    try:
        value = float(text)
    except ValueError:
        path = Path(text)
        if not path.exists():
            raise UserError(f"--scale {text!r} is neither a number nor an existing file") from None
        try:
            value = float(json.loads(path.read_text())["factor"])
        except (json.JSONDecodeError, KeyError, TypeError, ValueError, UnicodeDecodeError):
            raise UserError(f"{path}: not a `flockcal scale --json` file (no numeric 'factor')") from None
    if not (value > 0 and value < float("inf")):
        raise UserError(f"--scale must be a positive factor, got {value!r}")
    return value


def load_scaled_take(path: str, scale: str | None, command: str):
    """The take at `path`, its positions multiplied by the `--scale` factor if one was given, its hemisphere
    flips undone (`unfolded`)."""
    from dataclasses import replace

    from flockcal.solver.scale import apply_scale
    from flockcal.takes import load_take

    take = load_take(path)
    if scale is not None:
        take = replace(take, positions=apply_scale(take.positions, scale_factor(scale)))
    return unfolded(take, command, path)


def unfolded(take, command: str, path: str, hemisphere: str | None = None):
    """`take` with the hemisphere flips of a recording that did not track the hemisphere undone
    (flockcal/hemisphere_unfold.py), saying on stderr how many frames it unfolded; the take itself when
    there were none."""
    from flockcal.hemisphere_unfold import unfold_take

    take, how = unfold_take(take, hemisphere)
    note = how.summary(take.names)
    if note:
        print(f"flockcal {command}: {path}: {note}", file=sys.stderr)
    return take


def _hierarchy(path: str | None) -> dict | None:
    if path is None:
        return None
    try:
        data = json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise UserError(f"{path}: no such hierarchy file") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise UserError(f"{path}: not valid JSON ({exc})") from None
    if not isinstance(data, dict) or not all(isinstance(k, str) and isinstance(v, str) for k, v in data.items()):
        raise UserError(f"{path}: a hierarchy file is one JSON object {{child: parent}} of sensor names")
    return data


def fit_take(take, hierarchy: str | None = None, root: str | None = None, skeleton: str | None = None,
             with_free: bool = False):
    """Fit `take` for an output: with a saved skeleton file, a `{child: parent}` file, or a full search.

    Returns a Calibration (a saved skeleton's carries its `KnownFit` as `state`), its humanoid found from a
    sample of the take; `.to_dict()` gives the docs/design.md §5 dict. With
    `with_free`, returns (fit, free calibration of the same take), the free one judging whether the
    take moved enough (it is the fit itself unless a skeleton file was given).
    """
    from dataclasses import replace

    from flockcal.solver.accumulator import GramAccumulator
    from flockcal.solver.calibration import calibrate
    from flockcal.solver.humanoid import humanoid_for, take_sample
    from flockcal.solver.solve import solve

    acc = GramAccumulator(take.n_sensors)
    acc.add_poses(take.rotations, take.positions, take.valid)
    sample = take_sample(take).snapshot()
    if skeleton is not None:
        if hierarchy is not None or root is not None:
            raise UserError("--skeleton fixes the tree; leave out --hierarchy and --root")
        from flockcal.exports.skeleton import load_skeleton
        from flockcal.solver.known_skeleton import fit_saved

        known = fit_saved(load_skeleton(skeleton), acc, take.names)
        fit = replace(known.calibration(), state=known)
        fit = replace(fit, humanoid=humanoid_for(fit, sample))
        return (fit, calibrate(acc, names=list(take.names))) if with_free else fit
    fit = solve(acc, list(take.names), hierarchy=_hierarchy(hierarchy), root=root, sample=sample)
    return (fit, fit) if with_free else fit


def fitted_take(args, command: str):
    """The take of `args` and its fit, or (take, None) when it is too short or too still to fit and
    --allow-partial was not given (the warning is printed)."""
    from flockcal.commands.takecheck import stop_for, too_short, too_still

    from flockcal.atomic import check_output

    check_output(args.output)  # before the fit, which can take minutes
    take = load_scaled_take(args.take, args.scale, command)
    # Fitted first, so bad input (names, hierarchy, skeleton file) is reported as such before the take is judged.
    cal, free = fit_take(take, args.hierarchy, args.root, args.skeleton, with_free=True)
    if stop_for(command, args.take, too_short(take) or too_still(free), args.allow_partial):
        return take, None
    return take, cal


def _add_fit_options(p: argparse.ArgumentParser) -> None:
    from flockcal.commands.takecheck import add_option

    p.add_argument("take", help="take file (.npz, docs/design.md §5)")
    add_option(p)
    p.add_argument("--hierarchy", metavar="FILE.json", help="{child: parent} map: skip the topology search")
    p.add_argument("--root", metavar="NAME", help="root body of the tree")
    p.add_argument("--skeleton", metavar="FILE.json", help="a saved skeleton of this performer: fit placements only")
    p.add_argument("--scale", metavar="FACTOR|FILE", help="unit scale factor (or `flockcal scale --json` output)")


def cmd_scale(args) -> int:
    from flockcal.solver.scale import apply_scale, rigid_pair_scale
    from flockcal.takes import load_take, save_take

    if args.apply and args.output:
        from flockcal.atomic import check_output

        check_output(args.output)
    take = load_take(args.take)
    if args.sensors:
        names = [x.strip() for x in args.sensors.split(",")]
        if len(names) != 2 or not all(names):
            raise UserError(f"--sensors takes two names separated by a comma, got {args.sensors!r}")
    elif take.n_sensors == 2:
        names = list(take.names)
    else:
        raise UserError(f"the take has {take.n_sensors} sensors; name the rigid pair with --sensors A,B")
    a, b = (take.index(x) for x in names)
    est = rigid_pair_scale(
        take.positions[:, a],
        take.positions[:, b],
        args.distance,
        valid=take.valid[:, a] & take.valid[:, b],
        rotations_a=take.rotations[:, a],
        rotations_b=take.rotations[:, b],
        max_relative_std=args.max_spread,
    )
    if args.json:
        print(json.dumps({"sensors": names, **est.to_dict()}))
    else:
        print(
            f"scale factor {est.factor:.5f} ± {est.factor_stderr:.5f} (true / measured distance; multiply positions by it)\n"
            f"measured {est.measured_mean_m * 100:.2f} cm ± {est.measured_std_m * 100:.2f} cm over {est.frames} frames; "
            f"scaled: mean {args.distance * 100:.2f} cm, std {est.scaled_std_m * 100:.2f} cm"
        )
    if args.apply:
        if not args.output:
            raise UserError("--apply needs --output FILE for the rescaled take")
        later = load_take(args.apply)
        from dataclasses import replace

        save_take(args.output, replace(later, positions=apply_scale(later.positions, est.factor)))
        print(f"wrote {args.output} (positions × {est.factor:.5f})", file=sys.stderr)
    return 0


def cmd_report(args) -> int:
    from flockcal.exports.report import REPORT_STAGES, write_report
    from flockcal.markers import is_marker_take
    from flockcal.bars import Stages

    if is_marker_take(args.take):
        return report_markers(args)
    with Stages("report", ["fitting", *REPORT_STAGES]) as stages:
        stages.step("fitting")
        take, cal = fitted_take(args, "report")
        if cal is None:
            return PARTIAL_EXIT
        up, up_from = report_up(args.up)
        write_report(args.output, cal, take, source=Path(args.take).name, up=up, up_from=up_from, progress=stages.step)
    print(f"wrote {args.output}", file=sys.stderr)
    return 0


def report_up(given: str, marker_take=None) -> tuple[str, str]:
    """(up axis, where it comes from) for `report --up given`: as given; else (auto) the marker file's own
    (`MarkerTake.up`), else the Flock's transmitter frame, z down."""
    if given != "auto":
        return given, "--up"
    if marker_take is not None and marker_take.up is not None:
        return marker_take.up, marker_take.up_from
    return "-z", "the Flock's transmitter frame (give --up for another)"


def report_markers(args) -> int:
    """`flockcal report` on a marker take (.c3d, marker .npz): fitted as `flockcal fit-markers` fits it (the
    page adds its bodies, what was merged and why), the derived per-body poses as the take."""
    from flockcal.commands.markers import fit_marker_file
    from flockcal.exports.report import REPORT_STAGES, write_report
    from flockcal.bars import Stages
    from flockcal.solver.optical.pipeline import STAGES

    for option in ("hierarchy", "skeleton", "scale"):
        if getattr(args, option, None):
            raise UserError(f"--{option} applies to sensor takes; {args.take} is a marker take, whose skeleton "
                            f"comes from its markers (leave --{option} out)")
    with Stages("report", ["reading", *STAGES, "poses and JSON", *REPORT_STAGES]) as stages:
        marker_take, fit, _ = fit_marker_file(args.take, root=args.root, step=stages.step)
        up, up_from = report_up(args.up, marker_take)
        write_report(args.output, fit.calibration(), fit.take(), source=Path(args.take).name, up=up, up_from=up_from,
                     progress=stages.step)
    print(f"wrote {args.output}", file=sys.stderr)
    return 0


def _export(args, command: str, write) -> int:
    """Fit the take and write it through the fitted skeleton: `write(path, cal, take, rest)`."""
    from flockcal.bars import Stages

    with Stages(command, ["fitting", "writing"]) as stages:
        stages.step("fitting")
        take, cal = fitted_take(args, command)
        if cal is None:
            return PARTIAL_EXIT
        stages.step("writing")
        rest = int(args.rest) if args.rest.isdigit() else args.rest
        write(args.output, cal, take, rest)
    print(f"wrote {args.output}", file=sys.stderr)
    return 0


def cmd_export_bvh(args) -> int:
    from flockcal.exports.bvh import write_bvh

    return _export(args, "export-bvh",
                   lambda path, cal, take, rest: write_bvh(path, cal, take, units=args.units, up=args.up, rest=rest))


def cmd_export_gltf(args) -> int:
    from flockcal.atomic import check_output
    from flockcal.exports.gltf import binary_for, write_gltf

    from flockcal.exports.vrm import plain_rig_note

    check_output(args.output)
    binary_for(args.output, "-o")  # a wrong extension is told before the fit
    why = []
    code = _export(args, "export-gltf",
                   lambda path, cal, take, rest: why.append(write_gltf(path, cal, take, up=args.up, rest=rest)))
    if why and why[0]:
        print(plain_rig_note(args.output, why[0]), file=sys.stderr)
    return code


def cmd_skeleton(args) -> int:
    from flockcal.exports.skeleton import write_skeleton
    from flockcal.bars import Stages

    with Stages("skeleton", ["fitting", "writing"]) as stages:
        stages.step("fitting")
        take, cal = fitted_take(args, "skeleton")
        if cal is None:
            return PARTIAL_EXIT
        stages.step("writing")
        source = {"take": Path(args.take).name, "frames": take.n_frames, "rate_hz": take.rate_hz}
        if args.scale is not None:
            source["scale"] = scale_factor(args.scale)
        write_skeleton(args.output, cal, source, take=take)
    print(f"wrote {args.output}", file=sys.stderr)
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "scale",
        help="tracker unit scale from two sensors rigidly fixed a known distance apart",
        description="Estimate the tracker's unit scale factor (true / measured mean distance) and its spread "
        "from a take of two rigidly fixed sensors; apply it later with --scale.",
    )
    p.add_argument("take", help="take of the rigid pair (.npz)")
    p.add_argument("--distance", type=float, required=True, metavar="METRES", help="true distance between the sensors")
    p.add_argument("--sensors", metavar="A,B", help="the two sensors (default: the take's two sensors)")
    p.add_argument("--max-spread", type=float, default=0.05, metavar="FRACTION",
                   help="refuse the take if the distance std exceeds this fraction of its mean (default 0.05)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--apply", metavar="TAKE", help="also write this later take rescaled by the factor")
    p.add_argument("-o", "--output", metavar="OUT.npz", help="where --apply writes the rescaled take")
    p.set_defaults(func=cmd_scale)

    p = subparsers.add_parser("report", help="one self-contained HTML page of a take's calibration (sensor or marker take)")
    _add_fit_options(p)
    p.add_argument("-o", "--output", required=True, metavar="REPORT.html")
    p.add_argument("--up", default="auto", choices=["auto", "-z", "+z", "+y"],
                   help="the world's up axis (default auto: a C3D's own, +z unless its POINT:Z_SCREEN says; a marker "
                        ".npz's 'up' entry; else -z, the Flock's)")
    p.set_defaults(func=cmd_report)

    p = subparsers.add_parser("export-bvh", help="the take played through its fitted skeleton, as BVH")
    _add_fit_options(p)
    p.add_argument("-o", "--output", required=True, metavar="OUT.bvh")
    p.add_argument("--units", default="cm", choices=["cm", "m", "mm", "in"], help="file units (default cm)")
    p.add_argument("--up", default="-z", choices=["-z", "+z", "+y"], help="tracker world's up axis (default -z, the Flock's)")
    p.add_argument("--rest", default="first", metavar="first|sensor|FRAME",
                   help="the file's rest pose: the take's first frame (default), a frame number, or raw sensor axes")
    p.set_defaults(func=cmd_export_bvh)

    p = subparsers.add_parser("export-gltf", help="the fitted skeleton as a glTF 2.0 rig, the take as its animation")
    _add_fit_options(p)
    p.add_argument("-o", "--output", required=True, metavar="OUT.glb", help=".glb (binary) or .gltf (JSON)")
    p.add_argument("--up", default="-z", choices=["-z", "+z", "+y"], help="tracker world's up axis (default -z, the Flock's)")
    p.add_argument("--rest", default="tpose", metavar="tpose|first|sensor|FRAME",
                   help="the rig's rest (bind) pose: a VRM 1.0 humanoid's T-pose (default; the take's first frame when "
                        "the tree is not human-shaped), the take's first frame, a frame number, or raw sensor axes")
    p.set_defaults(func=cmd_export_gltf)

    p = subparsers.add_parser("skeleton", help="save the performer's calibrated skeleton for their next take")
    _add_fit_options(p)
    p.add_argument("-o", "--output", required=True, metavar="SKELETON.json")
    p.set_defaults(func=cmd_skeleton)
