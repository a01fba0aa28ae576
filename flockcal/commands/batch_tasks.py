"""What a Dask worker runs for `flockcal batch`: one take's result through the very functions `fit --json`
and `fit-markers --json` use (same bytes), its accumulator for --combine, the sum of accumulators and the
combined calibration. Plain functions of picklable arguments, importable wherever flockcal is installed.
"""

from __future__ import annotations

import math
import time
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from flockcal.errors import FlockcalError
from flockcal.malloc import roomy_malloc

SUFFIXES = (".npz", ".fobraw", ".c3d")
# A slip's onset is an estimate (design.md §4): the combined sums drop the slipped sensor's frames from this
# long before it, so no frame of the new placement can leak into the old one's sums.
SLIP_GUARD_S = 0.5
CHUNK = 65536  # frames per accumulator update (a multiple of its 256-frame block, as `flockcal fit` reads)


@dataclass(frozen=True)
class FitOptions:
    """The `fit` options a batch passes to every take (see `flockcal fit --help`)."""

    hierarchy: dict | None = None
    root: str | None = None
    tolerance: float = 0.005  # metres
    find_slips: bool = True
    allow_partial: bool = False
    combine: bool = False  # also build the take's contribution to the combined sums


@dataclass
class TakeOutcome:
    """One take's row of summary.csv, and its JSON text (None when it failed)."""

    path: str
    kind: str = ""  # "sensors" or "markers"
    text: str | None = None
    names: tuple[str, ...] = ()
    frames: int | None = None
    sensors: int | None = None
    root: str | None = None
    determined: int | None = None
    joints: int | None = None
    worst_rms_mm: float | None = None
    slips: int | None = None
    seconds: float = 0.0
    error: str = ""
    warning: str = ""  # a take fitted with --allow-partial although too short or too still
    extra: dict = field(default_factory=dict)


def warm_up() -> None:
    """Import the fitting code (run once on each worker, so no take pays for it)."""
    from flockcal.threads import single_threaded_blas

    single_threaded_blas()
    roomy_malloc()
    import flockcal.commands.fit  # noqa: F401
    import flockcal.solver.calibration  # noqa: F401
    import flockcal.solver.segments  # noqa: F401
    import flockcal.solver.slippage  # noqa: F401
    import flockcal.takes  # noqa: F401


def one_line(exc: BaseException) -> str:
    """An exception as the one line a person reads: flockcal's own errors as they are, anything else
    (a bug) with its type so it can be reported."""
    text = " ".join(str(exc).split())
    if isinstance(exc, FlockcalError):
        return text
    return f"internal error, please report it: {type(exc).__name__}: {text}"


def take_kind(path: str) -> str:
    """"sensors" (a take for `fit`) or "markers" (for `fit-markers`), from the suffix and, for an .npz,
    the arrays it names; a file flockcal cannot read raises a one-line error."""
    from flockcal.takes import TakeError

    p = Path(path)
    suffix = p.suffix.lower()
    if suffix not in SUFFIXES:
        raise TakeError(f"{p}: not a take (flockcal batch reads {', '.join(SUFFIXES)} files)")
    if not p.exists():
        raise TakeError(f"{p}: no such file")
    if suffix == ".c3d":
        return "markers"
    if suffix == ".fobraw":
        return "sensors"
    try:
        with zipfile.ZipFile(p) as z:
            arrays = {Path(n).stem for n in z.namelist()}
    except (OSError, zipfile.BadZipFile):
        return "sensors"  # load_take gives the precise error
    return "markers" if "markers" in arrays and "rotations" not in arrays else "sensors"


def load_sensor_take(path: str):
    """The `Take` `fit` reads: an .npz with its hemisphere flips undone as `fit` undoes them, a .fobraw as
    `flockcal convert` turns it into one."""
    if Path(path).suffix.lower() == ".fobraw":
        from flockcal.commands.record import recording_take

        return recording_take(path)
    from flockcal.hemisphere_unfold import unfold_take
    from flockcal.takes import load_take

    return unfold_take(load_take(path))[0]


def shared_origin(paths: list[str]) -> np.ndarray | None:
    """The origin every take's accumulator uses for --combine: the first valid frame's sensor centroid of
    the first sensor take that loads (only a common origin lets accumulators be summed); None when no
    take is one (there is nothing to combine, and the takes are still fitted)."""
    for path in paths:
        try:
            if take_kind(path) != "sensors":
                continue
            take = load_sensor_take(path)
        except FlockcalError:
            continue
        rows = np.flatnonzero(take.valid.any(axis=1))
        if rows.size:
            k = rows[0]
            return take.positions[k][take.valid[k]].mean(axis=0)
    return None


def fit_one(path: str, options: FitOptions, origin=None):
    """(TakeOutcome, contribution) for one take; the contribution is its GramAccumulator for --combine (None
    without --combine, for marker takes and for takes that failed). Never raises for a bad take."""
    from flockcal.threads import single_threaded_blas

    single_threaded_blas()  # a worker started without Dask's nanny may not have set it
    roomy_malloc()  # also on workers that joined the cluster after warm_up ran
    start = time.perf_counter()
    out = TakeOutcome(path)
    acc = None
    try:
        out.kind = take_kind(path)
        if out.kind == "markers":
            _fit_markers(path, options, out)
        else:
            acc = _fit_sensors(path, options, origin, out)
    except Exception as exc:  # noqa: BLE001 — every failure becomes the take's row; the others go on
        out.error, out.text, acc = one_line(exc), None, None
    out.seconds = time.perf_counter() - start
    return out, acc


def _fit_sensors(path: str, options: FitOptions, origin, out: TakeOutcome):
    from flockcal.commands.fit import calibrate_take, fit_result, json_text
    from flockcal.commands.takecheck import too_short, too_still

    take = load_sensor_take(path)
    cal = calibrate_take(take, hierarchy=options.hierarchy, root=options.root, tolerance=options.tolerance,
                         progress=False)
    problem = too_short(take) or too_still(cal)
    if problem and not options.allow_partial:
        raise PartialTake(f"{path} is {problem}; pass --allow-partial to fit it anyway")
    out.warning = problem or ""
    slips, result = fit_result(take, cal, tolerance=options.tolerance, find_slips=options.find_slips)
    d = result.to_dict()  # the §5 JSON, built once: the file's text and the summary row both read it
    out.text = json_text(d)
    out.names = tuple(take.names)
    _describe(out, d)
    if not options.combine:
        return None
    return contribution(take, d.get("slip_events", []), origin)


def _fit_markers(path: str, options: FitOptions, out: TakeOutcome) -> None:
    from flockcal.commands.markers import fit_marker_file, json_text

    _, _, result = fit_marker_file(path, root=options.root)
    out.text = json_text(result)
    out.names = tuple(result.get("sensors", ()))
    _describe(out, result)


class PartialTake(FlockcalError):
    """A take too short or too still to fit (fit's exit code 3), in a batch without --allow-partial."""


def _describe(out: TakeOutcome, result: dict) -> None:
    joints = result.get("joints", [])
    rms = [j.get("rms_m") for j in joints]
    rms = [x for x in rms if isinstance(x, (int, float)) and math.isfinite(x)]
    out.frames = int(result.get("frames", 0))
    out.sensors = len(result.get("sensors", ()))
    out.root = result.get("root")
    out.joints = len(joints)
    out.determined = sum(1 for j in joints if j.get("determined"))
    out.worst_rms_mm = 1000.0 * max(rms) if rms else None
    out.slips = len(result.get("slip_events", []))


def contribution_mask(take, events) -> np.ndarray:
    """The take's valid (n, m) with each slipped sensor's frames dropped from SLIP_GUARD_S before its first
    slip on (both sensors of a swap from the swap on): the combined calibration is of the placements the
    sensors had when the performer put them on, the one placement every take of the session shares."""
    valid = np.array(take.valid, dtype=bool)
    names = list(take.names)
    cut = np.full(len(names), np.inf)
    for e in events:
        t = float(e["time_s"])
        if e.get("kind") == "swap":
            hit = [x for x in e.get("candidates", []) if x in names]
            guard = 0.0
        else:
            hit = [e["sensor"]] if e.get("sensor") in names else []
            guard = SLIP_GUARD_S
        for x in hit:
            i = names.index(x)
            cut[i] = min(cut[i], t - guard)
    for i in np.flatnonzero(np.isfinite(cut)):
        valid[np.asarray(take.times) >= cut[i], i] = False
    return valid


def contribution(take, events, origin):
    """The take's GramAccumulator for --combine, with the shared `origin`; its own accumulator, so no
    frame pair, score block or jitter window spans two takes when they are summed."""
    from flockcal.solver.accumulator import GramAccumulator

    acc = GramAccumulator(take.n_sensors, origin=origin)
    valid = contribution_mask(take, events)
    for s in range(0, take.n_frames, CHUNK):
        e = min(take.n_frames, s + CHUNK)
        acc.add_poses(take.rotations[s:e], take.positions[s:e], valid[s:e])
    return acc


def merged(*accumulators):
    """The sum of accumulators (a node of the tree sum on the workers)."""
    total = accumulators[0].copy()
    for acc in accumulators[1:]:
        total.merge(acc)
    return total


def combined_text(acc, names: tuple[str, ...], options: FitOptions, takes: list[str], left_out: list[dict]) -> str:
    """combined.json: the §5 object of the summed accumulator (slips were handled per take, so
    `slip_events` is empty), plus `takes` (the files combined) and `left_out` ({take, reason})."""
    from flockcal.commands.fit import json_text
    from flockcal.solver.calibration import calibrate

    cal = calibrate(acc, hierarchy=options.hierarchy, root=options.root, names=names, tolerance=options.tolerance)
    result = cal.to_dict()
    result["takes"] = list(takes)
    result["left_out"] = list(left_out)
    return json_text(result)
