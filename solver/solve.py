"""The one place that decides how a take is fitted: plain, with a saved skeleton, or segmented after slips.

`solve` fits an accumulator (the live fit worker, session stop, `flockcal fit`); `solve_take` a recorded
take with the slip events found or stored for it (session resolve, `flockcal fit` after its slip search).
Both return the solver's `Calibration`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

from flockcal.solver.calibration import Calibration, calibrate
from flockcal.solver.fits import TOLERANCE_M


def solve(acc, names: Sequence[str], hierarchy=None, root=None, skeleton=None, tolerance: float = TOLERANCE_M,
          previous: Calibration | None = None, slip_events=None) -> Calibration:
    """Fit accumulator `acc` (an `Accumulator`: plain or segmented) for sensors `names`.

    With a saved `skeleton` (a `flockcal.exports.skeleton.Skeleton`) only the placements are fitted, its
    tree and bones kept, warm-started from `previous` (the last such result of the same session); with
    open slip segments every joint of a slipped sensor is fitted on the frames since its slip; otherwise
    the tree is the given `hierarchy` or searched (from `root`). `slip_events` are recorded in the result.
    """
    from flockcal.solver.known_skeleton import known_calibration, known_fit

    names = list(names)
    events = tuple(slip_events or ())
    if skeleton is not None:
        start = None if previous is None else previous.state
        fit = known_fit(skeleton, acc, names, start)
        return replace(known_calibration(fit, acc), state=fit, slip_events=events)
    if acc.segments:
        return acc.calibration(hierarchy=hierarchy, root=root, names=names, slip_events=events, tolerance=tolerance)
    cal = calibrate(acc.whole_take, hierarchy=hierarchy, root=root, names=names, tolerance=tolerance)
    return replace(cal, slip_events=events) if events else cal


def solve_take(take, events=(), hierarchy=None, root=None, skeleton=None, tolerance: float = TOLERANCE_M) -> Calibration:
    """Fit a recorded `take` (a `flockcal.takes.Take`) given its slip `events` (SlipEvent/SwapEvent, or
    stored events with time_s and sensor_index): each slipped sensor's joints on the frames since its
    (latest) slip, everything else on the whole take; `solve` decides the rest."""
    from flockcal.solver.segments import segmented_from_take

    acc = segmented_from_take(take, list(events))
    return solve(acc, take.names, hierarchy, root, skeleton, tolerance, slip_events=events)
