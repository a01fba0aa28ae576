"""`flockcal fit FILE.npz`: calibrate a recorded take (joints, hinge axes, bones, topology) as a table or JSON.

Reads the .npz interchange of docs/design.md §5, feeds it to the Gram accumulator and prints the calibration;
--json prints exactly the §5 object. Bad files and bad hierarchies end in one line naming the problem.
"""

from __future__ import annotations

import argparse
import json
import sys
from contextlib import contextmanager
from pathlib import Path

from flockcal.commands.takecheck import PARTIAL_EXIT, add_option, stop_for, too_short, too_still
from flockcal.errors import UserError
from flockcal.bars import Stages


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "fit",
        help="find joints, bones and the skeleton tree in a recorded take",
        description="Fit joint centres, hinge axes, bone lengths and the skeleton tree to a take (.npz, docs/design.md §5).",
    )
    p.add_argument("file", metavar="FILE.npz", help="recorded take")
    p.add_argument("--hierarchy", metavar="MAP.json", help='a {"child": "parent", …} map (root omitted): fit only those joints')
    p.add_argument("--root", metavar="NAME", help="hang the tree from this sensor (default: the body that splits it most evenly)")
    p.add_argument("--json", action="store_true", help="print the JSON object of docs/design.md §5 instead of a table")
    p.add_argument("--bvh", metavar="OUT.bvh", help="also write the take as BVH through the fitted skeleton")
    p.add_argument("--gltf", metavar="OUT.glb", help="also write the fitted skeleton as a glTF 2.0 rig (skin, figure "
                   "and the take as its animation; .glb or .gltf), a VRM 1.0 humanoid when the tree is human-shaped")
    p.add_argument("--trc", metavar="OUT.trc", help="also write the joint centres over the take as TRC virtual markers "
                   "(millimetres; OpenSim reads it)")
    p.add_argument("--scale", metavar="FACTOR", help="multiply positions by FACTOR before fitting (unit scale, paper §4): "
                   "a number or the JSON file `flockcal scale --json` wrote")
    p.add_argument("--no-slips", action="store_true", help="skip the sensor-slip search (faster on long takes)")
    p.add_argument("--max-take-gb", type=float, metavar="GB",
                   help="refuse a take whose arrays unpack to more than GB gigabytes (default: $FLOCKCAL_MAX_TAKE_GB, "
                        "else 4; the take is read a chunk at a time whatever its size)")
    add_option(p)
    add_tolerance(p)
    p.set_defaults(func=run)


def add_tolerance(p) -> None:
    """The --tolerance-mm option `fit` and `serve` share (docs/design.md §3a)."""
    p.add_argument("--tolerance-mm", type=float, default=5.0, metavar="MM",
                   help="a joint counts as determined when the data pin its centre to within MM along every "
                        "direction it needs (default 5)")


def tolerance_m(args: argparse.Namespace) -> float:
    """--tolerance-mm in metres; UserError unless it is a positive number."""
    mm = float(args.tolerance_mm)
    if not mm > 0 or mm != mm or mm == float("inf"):
        raise UserError(f"--tolerance-mm must be a positive number of millimetres, got {args.tolerance_mm}")
    return mm / 1000.0


def load_hierarchy(path: str) -> dict:
    """The {child: parent} map from a JSON file; UserError for a missing or malformed file."""
    p = Path(path)
    if not p.exists():
        raise UserError(f"{p}: no such hierarchy file")
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise UserError(f"{p}: not a readable JSON hierarchy ({exc})") from None
    if not isinstance(data, dict) or not data:
        raise UserError(f'{p}: a hierarchy must be a JSON object {{"child": "parent", …}} with at least one joint')
    for child, parent in data.items():
        if not (parent is None or isinstance(parent, str)):
            raise UserError(f"{p}: the parent of {child!r} must be a sensor name (or null for the root), got {parent!r}")
    return data


@contextmanager
def accumulating(take, progress: bool = True):
    """The bar over a take's frames as they are summed, on a terminal once it takes a while: yields its update."""
    from flockcal.bars import bar

    with bar(take.n_frames, "accumulating", unit="frame", unit_scale=True) as shown:
        shown.disable = shown.disable or not progress
        yield shown.update


def accumulate(take, progress: bool = True):
    """A GramAccumulator over the whole take, with a progress bar on a terminal once it takes a while."""
    from flockcal.solver.take_fit import accumulate_take

    with accumulating(take, progress) as update:
        return accumulate_take(take, on_frames=update)


def run(args: argparse.Namespace) -> int:
    from flockcal.threads import single_threaded_blas

    single_threaded_blas()  # before numpy loads
    from flockcal.atomic import check_output
    from flockcal.take_files import ScaledTake, TakeFile

    if args.bvh:
        check_output(args.bvh, "--bvh")  # before the fit, which can take minutes
    if args.gltf:
        from flockcal.exports.gltf import binary_for

        check_output(args.gltf, "--gltf")
        binary_for(args.gltf, "--gltf")
    if args.trc:
        check_output(args.trc, "--trc")
    # Read a chunk at a time, as often as the fit needs (memory stays a chunk: docs/cli.md#memory).
    take = TakeFile(args.file, args.max_take_gb)
    if args.scale is not None:
        from flockcal.commands.outputs import scale_factor

        take = ScaledTake(take, scale_factor(args.scale))
    from flockcal.commands.outputs import unfolded

    take = unfolded(take, "fit", args.file)
    hierarchy = load_hierarchy(args.hierarchy) if args.hierarchy else None
    # Fitted first, so bad input (names, hierarchy) is reported as such before the take is judged.
    tol = tolerance_m(args)
    cal = calibrate_take(take, hierarchy=hierarchy, root=args.root, tolerance=tol)
    if stop_for("fit", args.file, too_short(take) or too_still(cal), args.allow_partial):
        return PARTIAL_EXIT
    plain = ""  # why the glTF rig is no VRM humanoid, when it is not
    with Stages("fit", ["searching for slips", "re-fitting after slips", "writing BVH", "writing glTF",
                        "writing TRC"]) as stages:
        slips, result = fit_result(take, cal, tolerance=tol, find_slips=not args.no_slips, step=stages.step)
        if args.bvh:
            from flockcal.exports.bvh import write_bvh  # here: scipy.spatial costs every fit ~0.3 s to import

            stages.step("writing BVH")
            write_bvh(args.bvh, cal, take)
        if args.gltf:
            from flockcal.exports.gltf import write_gltf

            stages.step("writing glTF")
            plain = write_gltf(args.gltf, cal, take)  # the skeleton the BVH plays, so the two files agree
        if args.trc:
            from flockcal.exports.trc import write_trc

            stages.step("writing TRC")
            write_trc(args.trc, cal, take)
    for path in (args.bvh, args.gltf, args.trc):
        if path:
            print(f"wrote {path}", file=sys.stderr)
    warn_conflicts(result)
    if plain:
        from flockcal.exports.vrm import plain_rig_note

        print(plain_rig_note(args.gltf, plain), file=sys.stderr)
    if args.json:
        sys.stdout.write(json_text(result))
    else:
        print(table(cal, source=args.file))
        if slips:
            print(slip_table(slips, result))
    return 0


# The fit path in parts (the solver's `take_fit`, which `flockcal.fit` runs whole), shared with `flockcal
# batch` (flockcal/commands/batch_tasks.py) so that a take's batch result is byte for byte what `fit --json` prints.
def calibrate_take(take, hierarchy: dict | None = None, root: str | None = None, tolerance: float = 0.005,
                   progress: bool = True):
    """The whole-take `Calibration` of `take` (accumulated in chunks, bar on a terminal), by `solve`."""
    from flockcal.solver.take_fit import fit_whole_take

    with accumulating(take, progress) as update:
        return fit_whole_take(take, hierarchy=hierarchy, root=root, tolerance=tolerance, on_frames=update)


def fit_result(take, cal, tolerance: float = 0.005, find_slips: bool = True, step=None) -> tuple[list, object]:
    """(slip events, the `Calibration` whose §5 JSON `fit --json` prints) for a take and its whole-take
    calibration: the solver's `refit_after_slips`, or no search at all (--no-slips)."""
    from flockcal.solver.take_fit import refit_after_slips

    return refit_after_slips(take, cal, tolerance=tolerance, step=step) if find_slips else ([], cal)


def warn_conflicts(cal) -> None:
    """One warning line on stderr for each sensor whose name says another bone than the data found."""
    from flockcal.solver.humanoid import conflict_message

    hum = cal.humanoid
    for x in (hum.conflicts if hum is not None else ()):
        print(f"warning: {conflict_message(cal.names, x)}", file=sys.stderr)


def json_text(result) -> str:
    """The exact text `fit --json` prints for a `Calibration` (or a §5 dict built from one)."""
    return json.dumps(result if isinstance(result, dict) else result.to_dict(), indent=2) + "\n"


def slip_table(slips, result) -> str:
    """Slip and swap events, and the joints re-fitted from each slip on (`result`: the Calibration after them)."""
    out = ["", "Sensor slips (joints of a slipped sensor are re-fitted from the slip on in --json)"]
    for e in slips:
        d = e.to_dict()
        who = " or ".join(d["candidates"]) if len(d.get("candidates") or []) > 1 else d["sensor"]
        kind = "swap" if d.get("kind") == "swap" else "slip"
        out.append(f"  {d['time_s']:7.2f} s  {kind} of {who}: jump {d['jump_mm']:.0f} mm at joints {', '.join(d['joints'])}")
    import numpy as np

    nm, J = result.names, result.joints
    start = result.segment_start_s if result.segment_start_s is not None else np.full(len(J), np.nan)
    for k in np.flatnonzero(np.isfinite(start)):
        out.append(f"    re-fitted from {start[k]:.2f} s: {nm[J.pairs[k, 0]]}–{nm[J.pairs[k, 1]]}  c {_cm(J.c[k])}  l {_cm(J.l[k])}")
    return "\n".join(out)


def _cm(v) -> str:
    return "(" + ", ".join("   —  " if x != x else f"{100 * x:6.2f}" for x in v) + ")"


def _mm(x) -> str:
    return "—" if x != x or x == float("inf") else f"{1000 * x:.2f}"


def table(cal, source: str = "") -> str:
    """The readable report: topology as an indented tree, joints, bones in cm, loops and warnings."""
    import numpy as np

    from flockcal.names import names_joint

    nm = cal.names
    J = cal.joints
    jname = cal.joint_names()
    hum = cal.humanoid
    bone = {i: f" [{b}]" for i, b in enumerate(hum.bones) if b is not None} if hum is not None else {}
    row = {int(c): k for k, c in enumerate(J.pairs[:, 0])}
    how = "given hierarchy" if cal.hierarchy_given else "searched (minimum spanning tree)"
    out = [f"{source}: {cal.frames} frames, {cal.n_sensors} sensors; topology {how}, root {nm[cal.root]}", ""]
    if hum is not None:
        out += ["Humanoid: " + ("every body's bone found from the tree and the take's motion [in brackets]"
                                if hum.human else hum.reason), ""]
    out.append("Topology")
    depth = np.zeros(cal.n_sensors, dtype=int)
    for x in cal.order:
        depth[x] = 0 if cal.parent[x] < 0 else depth[cal.parent[x]] + 1
    stack, dfs = [int(cal.root)], []
    while stack:  # depth first, so each child prints under its parent
        x = stack.pop()
        dfs.append(x)
        stack.extend(sorted(np.flatnonzero(cal.parent == x).tolist(), reverse=True))
    for x in dfs:
        p = cal.parent[x]
        if p < 0:
            note = "root"
        elif x in row:
            k = row[x]
            kind = "hinge" if J.hinge[k] else "ball" if J.determined[k] else "undetermined"
            note = f"{kind}, rms {_mm(J.rms[k])} mm"
            if (hum is not None and hum.human) or names_joint(nm[x], nm[p]):
                note = f"{jname[k]}: {note}"
        else:
            note = f"rigid with {nm[p]}"
        out.append(f"  {'  ' * depth[x]}{nm[x]}{bone.get(x, '')}  ({note})")
    width = max([5] + [len(x) for x in jname])
    out += ["", "Joints (c in the child's frame, l in the parent's; cm)"]
    out.append(f"  {'joint':<{width}} {'child':<12} {'parent':<12} {'c':<26} {'l':<26} {'rms mm':>7} {'±c mm':>6} "
               f"{'coverage (least first)':<24} axis (child frame)")
    for k in range(len(J)):
        cov = " ".join(f"{x:.3f}" for x in J.coverage[k])
        axis = " ".join(f"{x:+.3f}" for x in J.axis_i[k]) if J.hinge[k] else ""
        out.append(
            f"  {jname[k]:<{width}} {nm[J.pairs[k, 0]]:<12} {nm[J.pairs[k, 1]]:<12} {_cm(J.c[k]):<26} {_cm(J.l[k]):<26} "
            f"{_mm(J.rms[k]):>7} {_mm(J.c_stderr[k]):>6} {cov:<24} {axis}"
        )
    b = cal.bones
    out += ["", "Bones (cm)"]
    if not len(b):
        out.append("  none (no body has two joints)")
    else:
        # A bone runs between two joints of one body; joints are named by their child body.
        spans = [f"{nm[b.from_joint[k]]} → {nm[b.to_joint[k]]}" for k in range(len(b))]
        width = max(len(x) for x in spans)
        out.append(f"  {'body':<12} {'between joints':<{width}} {'length':>8}   {'±':>5}")
        for k in range(len(b)):
            out.append(f"  {nm[b.body[k]]:<12} {spans[k]:<{width}} {100 * b.length[k]:8.3f}   {100 * b.stderr[k]:5.3f}")
    if cal.loop_candidates:
        out += ["", "Loop candidates (pairs outside the tree that fit like joints)"]
        out += [f"  {nm[a]} – {nm[bb]}  rms {_mm(r)} mm" for a, bb, r in cal.loop_candidates]
    if cal.rigid_groups:
        out += ["", "Rigid groups (never turned relative to each other: one body, not a joint)"]
        out += ["  " + ", ".join(nm[i] for i in g) for g in cal.rigid_groups]
    if cal.ambiguous:
        out += ["", "Ambiguous parents (the tree picked the first; the data cannot tell them apart)"]
        out += [f"  {nm[c]}: {', '.join(nm[p] for p in ps)} — {note}" for c, ps, note in cal.ambiguous]
    under = [k for k in range(len(J)) if not J.determined[k]]
    if under:
        names = ", ".join(jname[k] for k in under)
        out += ["", f"Move more: {names} — not determined yet (the data do not pin the centre to the tolerance); "
                "no bone ends there"]
    return "\n".join(out)
