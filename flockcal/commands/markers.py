"""`flockcal fit-markers take.c3d|take.npz`: a skeleton from optical markers alone (Kirk et al. 2005).

Prints a table, or with --json the object of `flockcal fit --json` (docs/design.md §5) plus "bodies"
{label: [marker names]}; --take writes the derived per-body poses as a take .npz for `flockcal fit`.
"""

from __future__ import annotations

import json
import math
import sys

from flockcal.errors import UserError


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "fit-markers",
        help="find rigid bodies, joints, bones and the tree from optical marker positions",
        description="Fit a skeleton to optical marker trajectories (.c3d or the marker .npz of docs/design.md §5).",
    )
    p.add_argument("file", metavar="TAKE", help="marker take: .c3d or .npz (markers, marker_names, rate_hz)")
    p.add_argument("--json", action="store_true", help="print the JSON object (fit --json shape plus 'bodies')")
    p.add_argument("--bodies", type=int, metavar="N", help="number of rigid bodies (default: chosen from the data)")
    p.add_argument("--root", metavar="LABEL", help="hang the tree from this body label")
    p.add_argument("--rigid-mm", type=float, default=None, metavar="MM",
                   help="relative motion (10-90 %% range) soft tissue makes: within it, with no joint pinned, groups are one body; default 15")
    p.add_argument("--take", metavar="OUT.npz", help="also write the per-body poses as a take .npz (for fit, exports)")
    p.add_argument("--salvage", action="store_true",
                   help="fit the frames a C3D file cut short still holds (refused without it), with a warning")
    p.set_defaults(func=run)


# How the table names each kind of merge (articulation.Verdict.kind).
MERGE_WORDS = {
    "skin": "turned within their soft tissue's noise",
    "twist": "twisting about their own length",
    "moved": "moved within the tolerance with no joint pinned",
    "unjudged": "too small to judge, within the tolerance",
}


def _clean(x):
    """JSON has no NaN: a number that could not be estimated is written as null."""
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, dict):
        return {k: _clean(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_clean(v) for v in x]
    return x


def fit_marker_file(path, bodies: int | None = None, root: str | None = None, step=None, salvage: bool = False,
                    **options):
    """(marker take, MarkerFit, the JSON dict `fit-markers --json` prints) for a .c3d or marker .npz;
    shared with `flockcal batch` so both print the same bytes. `salvage` fits what a cut-short C3D holds
    (flockcal.markers.load_c3d); `options` go to `fit_markers` (`rigid_tolerance`)."""
    from flockcal.markers import load_markers
    from flockcal.solver.optical.pipeline import fit_markers

    step = step or (lambda name: None)
    step("reading")
    take = load_markers(path, salvage=salvage)
    fit = fit_markers(take.markers, take.marker_names, take.rate_hz, take.times, n_groups=bodies,
                      root=root, progress=step, **options)
    step("poses and JSON")
    return take, fit, _clean(fit.to_dict())


def json_text(out: dict) -> str:
    """The exact text `fit-markers --json` prints."""
    return json.dumps(out) + "\n"


def run(args) -> int:
    from flockcal.bars import Stages
    from flockcal.solver.optical.pipeline import STAGES

    if args.bodies is not None and args.bodies < 2:
        raise UserError(f"--bodies must be 2 or more, got {args.bodies}")
    if args.rigid_mm is not None and not (args.rigid_mm > 0 and math.isfinite(args.rigid_mm)):
        raise UserError(f"--rigid-mm must be a positive number of millimetres, got {args.rigid_mm}")
    extra = {} if args.rigid_mm is None else {"rigid_tolerance": args.rigid_mm / 1000.0}
    if args.take:
        from flockcal.atomic import check_output

        check_output(args.take, "--take")
    with Stages("fit-markers", ["reading", *STAGES, "poses and JSON"]) as stages:
        take, fit, out = fit_marker_file(args.file, bodies=args.bodies, root=args.root, step=stages.step,
                                         salvage=args.salvage, **extra)
        if args.take:
            from flockcal.takes import save_take

            save_take(args.take, fit.take())
    if take.declared_frames is not None:
        print(f"flockcal fit-markers: warning: {args.file} ends early: fitted the {take.n_frames} frames it holds "
              f"of the {take.declared_frames} its header declares (--salvage)", file=sys.stderr)
    if args.take:
        print(f"wrote {args.take}", file=sys.stderr)
    if args.json:
        sys.stdout.write(json_text(out))
        return 0
    w = sys.stdout.write
    w(f"{take.source}: {take.n_markers} markers, {take.n_frames} frames at {take.rate_hz:g} Hz\n")
    w(f"bodies ({len(out['bodies'])}), root {out['root']}:\n")
    for label, names in out["bodies"].items():
        parent = out["parent"].get(label, "-")
        motion = out["body_motion_m"].get(label) or 0.0
        w(f"  {label:<16} parent {parent:<16} {motion * 1000:5.1f} mm  markers {', '.join(names)}\n")
    w(f"  (mm: mean relative motion inside the body; within {out['rigid_tolerance_m'] * 1000:g} mm and no joint pinned, "
      "groups are one body; a joint that moves separates them at any size)\n")
    for label, info in out.get("merged", {}).items():
        kinds = {}
        for mg in info["merges"]:
            kinds[mg["verdict"]] = kinds.get(mg["verdict"], 0) + 1
        why = ", ".join(f"{n} {MERGE_WORDS.get(k, k)}" for k, n in kinds.items())
        w(f"merged into {label}: {len(info['parts'])} rigid part(s), {why} (--json \"merged\" says why, each)\n")
    for f in out.get("joints_fitted_on", []):
        w(f"joint {f['joint'][0]}–{f['joint'][1]} fitted on {', '.join(f['child_markers'])} | {', '.join(f['parent_markers'])}\n")
    joints = ", ".join(f"{c}–{p}" for c, p in out["exercised_joints"]) or "none"
    w(f"joints the take exercised (centre pinned within {out['joint_tolerance_m'] * 1000:g} mm): {joints}\n")
    if out.get("pair_fit_joints"):
        w(f"placed by the pair fit over the bodies' poses (the others by Kirk's fit): "
          f"{', '.join(f'{c}–{p}' for c, p in out['pair_fit_joints'])}\n")
    if out["kirk_only_joints"]:
        w(f"joints to bodies under three markers (Kirk fit only): {', '.join(f'{c}–{p}' for c, p in out['kirk_only_joints'])}\n")
    if out["unjoined"]:
        w(f"no exercised joint reaches: {', '.join(out['unjoined'])}\n")
    # A bone runs between two joints of one body: a tree of one joint (the knee trial) has none.
    w("bones:" + ("\n" if out["bones"] else " none (no body has two joints in the tree)\n"))
    for b in out["bones"]:
        w(f"  {b['body']:<16} {str(b['from_joint']):>16} → {b['to_joint']:<16} {b['length_m'] * 1000:8.1f} mm\n")
    for e in out["swap_events"]:
        w(f"marker swap {e['time_s']:.2f}–{e['stop_s']:.2f} s: {e['markers'][0]} ↔ {e['markers'][1]}\n")
    if out["unused_markers"]:
        w(f"left out (seen too rarely): {', '.join(out['unused_markers'])}\n")
    return 0
