"""The one place that decides how a take is fitted: plain, with a saved skeleton, or segmented after slips;
and, given a sample of the take's frames, which humanoid bone each body is, the tree then hung from the hips.

`solve` fits an accumulator (the live fit worker, session stop, `flockcal fit`); `solve_take` a recorded
take with the slip events found or stored for it (session resolve, `flockcal fit` after its slip search).
Both return the solver's `Calibration`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from flockcal.solver.calibration import Calibration, calibrate
from flockcal.solver.fits import TOLERANCE_M
from flockcal.solver.humanoid import Humanoid, Sample, humanoid_for
from flockcal.solver.topology import orient


def solve(acc, names: Sequence[str], hierarchy=None, root=None, skeleton=None, tolerance: float = TOLERANCE_M,
          previous: Calibration | None = None, slip_events=None, sample: Sample | None = None,
          humanoid: Humanoid | None = None) -> Calibration:
    """Fit accumulator `acc` (an `Accumulator`: plain or segmented) for sensors `names`.

    With a saved `skeleton` (a `flockcal.exports.skeleton.Skeleton`) only the placements are fitted, its
    tree and bones kept, warm-started from `previous` (the last such result of the same session); with
    open slip segments every joint of a slipped sensor is fitted on the frames since its slip; otherwise
    the tree is the given `hierarchy` or searched (from `root`). `slip_events` are recorded in the result.

    `sample` (a `humanoid.Sample` of the take's frames) finds which humanoid bone each body is
    (`Calibration.humanoid`); `humanoid` (by default `previous.humanoid`), the last one found for this take,
    is kept while the tree and the sample have not changed enough to matter (`humanoid.humanoid_for`). A
    human tree is hung from its hips unless `root` names another body (a given hierarchy is turned to hang
    from the hips; a saved skeleton keeps its root).
    """
    names = list(names)
    hint = humanoid if humanoid is not None else previous.humanoid if previous is not None else None
    hips = None
    if root is None and skeleton is None and hint is not None and hint.human:
        hips = hint.sensor("hips")  # last fit's hips: most fits find them again, and need no second fit
    cal = _fit(acc, names, hierarchy, root if hips is None else hips, skeleton, tolerance, previous, slip_events)
    if sample is None and hint is None:
        return cal
    hum = humanoid_for(cal, sample, hint)
    if hum is None:
        return cal
    if hum.human and root is None and skeleton is None and cal.root != hum.sensor("hips"):
        cal = _fit(acc, names, hierarchy, hum.sensor("hips"), skeleton, tolerance, previous, slip_events, again=cal)
    return replace(cal, humanoid=hum)


def _fit(acc, names: list, hierarchy, root, skeleton, tolerance: float, previous, slip_events,
         again: Calibration | None = None) -> Calibration:
    """One fit as `solve` decides it; `again`: the same accumulator's fit with another root, whose all-pair
    fits a plain fit hangs from `root` without fitting them again."""
    from flockcal.solver.known_skeleton import known_calibration, known_fit

    events = tuple(slip_events or ())
    if skeleton is not None:
        start = None if previous is None else previous.state
        fit = known_fit(skeleton, acc, names, start)
        return replace(known_calibration(fit, acc), state=fit, slip_events=events)
    if hierarchy is not None and root is not None:
        hierarchy = hung_from(hierarchy, names, root)
    if acc.segments:
        return acc.calibration(hierarchy=hierarchy, root=root, names=names, slip_events=events, tolerance=tolerance)
    fits = again.fits if again is not None and hierarchy is None else None
    cal = calibrate(acc.whole_take, hierarchy=hierarchy, root=root, names=names, tolerance=tolerance, fits=fits)
    return replace(cal, slip_events=events) if events else cal


def hung_from(hierarchy, names: Sequence[str], root) -> np.ndarray:
    """The tree of `hierarchy` (a {child: parent} map or a parent array) hung from `root` instead: the same
    joints, the path from its root to `root` turned round. A parent array."""
    from flockcal.solver.hierarchy import parse_hierarchy, sensor_index

    parent = parse_hierarchy(hierarchy, names)
    r = sensor_index(root, names, "root")
    kids = np.flatnonzero(parent >= 0)
    turned, _ = orient(np.stack([kids, parent[kids]], axis=1), len(names), r)
    return turned


def solve_take(take, events=(), hierarchy=None, root=None, skeleton=None, tolerance: float = TOLERANCE_M,
               sample: Sample | None = None, humanoid: Humanoid | None = None) -> Calibration:
    """Fit a recorded `take` (a `flockcal.takes.Take`) given its slip `events` (SlipEvent/SwapEvent, or
    stored events with time_s and sensor_index): each slipped sensor's joints on the frames since its
    (latest) slip, everything else on the whole take; `solve` decides the rest. `sample`, `humanoid`: the
    take's sample and the humanoid found on it before the slips (kept if the tree is the same)."""
    from flockcal.solver.segments import segmented_from_take

    acc = segmented_from_take(take, list(events))
    return solve(acc, take.names, hierarchy, root, skeleton, tolerance, slip_events=events, sample=sample,
                 humanoid=humanoid)
