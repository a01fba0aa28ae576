"""A recorded take's whole fit, the path `flockcal fit` runs: accumulate, solve, search for slips, re-solve.

`fit(take)` is that path in one call (`flockcal.fit`); `fit_whole_take` and `refit_after_slips` are its
two halves, for callers that look at the whole-take fit before the slip search (the CLI stops a take too
still to fit there, and draws its exports from it).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

from flockcal.solver.accumulator import GramAccumulator
from flockcal.solver.calibration import Calibration
from flockcal.solver.fits import TOLERANCE_M
from flockcal.solver.solve import solve

def accumulate_take(take, on_frames: Callable[[int], object] | None = None) -> GramAccumulator:
    """A `GramAccumulator` over every frame of `take` (a `Take` or any `ChunkedTake`), read `chunk_frames`
    at a time (about 8 MB of arrays, a multiple of the accumulator's block: the sums are one pass's, and a
    take file's memory stays a chunk); `on_frames(k)` is told each time k more frames are in (a progress
    bar's `update`)."""
    from flockcal.frames import chunk_frames, frames_of

    acc = GramAccumulator(len(take.names))
    for frames in frames_of(take, chunk_frames(len(take.names))):
        acc.add_poses(frames.rotations, frames.positions, frames.valid)
        if on_frames is not None:
            on_frames(len(frames))
    return acc


def fit_whole_take(take, *, hierarchy: Mapping | None = None, root: str | None = None,
                   tolerance: float = TOLERANCE_M, on_frames: Callable[[int], object] | None = None) -> Calibration:
    """The `Calibration` of every frame of `take` together, by `solve`: the first half of `fit`. Its humanoid
    is found from a sample of the take (a human tree hung from its hips unless `root` is given)."""
    from flockcal.solver.humanoid import take_sample

    acc = accumulate_take(take, on_frames)
    return solve(acc, take.names, hierarchy=hierarchy, root=root, tolerance=tolerance,
                 sample=take_sample(take).snapshot())


def refit_after_slips(take, calibration: Calibration, *, tolerance: float = TOLERANCE_M,
                      step: Callable[[str], object] | None = None) -> tuple[list, Calibration]:
    """(slip and swap events, the fit after them) for `take` and its whole-take `calibration`: the second
    half of `fit`.

    The slipped sensors' joints and bones are re-fitted on the frames since their slip (docs/design.md §4);
    everything else keeps the whole take. Without a slip the calibration comes back as it is. `step(name)`
    is told each stage as it starts ("searching for slips", "re-fitting after slips").
    """
    if not len(calibration.joints.pairs):
        return [], calibration
    from flockcal.solver.humanoid import take_sample
    from flockcal.solver.slippage import detect_slips
    from flockcal.solver.solve import solve_take

    step = step or (lambda name: None)
    step("searching for slips")
    slips = detect_slips(take, calibration)
    if not slips:
        return slips, calibration
    step("re-fitting after slips")
    result = solve_take(take, slips, hierarchy=calibration.parent_map(), root=calibration.names[calibration.root],
                        tolerance=tolerance, sample=take_sample(take).snapshot(), humanoid=calibration.humanoid)
    return slips, result


def fit(take, *, hierarchy: Mapping[str, str] | None = None, root: str | None = None,
        tolerance: float = TOLERANCE_M, slips: bool = True) -> Calibration:
    """Fit a recorded take: joint centres, hinge axes, bones and the skeleton's tree.

    The same path as ``flockcal fit``: every frame summed into one Gram accumulator, the tree searched (or
    the given one fitted), then a search for sensor slips and, after one, the slipped sensors' joints
    re-fitted on the frames since the slip. ``fit(take).to_dict()`` is the object ``flockcal fit --json``
    prints (docs/design.md §5).

    Parameters
    ----------
    take : Take or ChunkedTake
        The recorded frames: a `flockcal.Take` (``flockcal.load_take(path)``), or anything that reads a
        take a chunk of frames at a time (`flockcal.takes.ChunkedTake`).
    hierarchy : mapping of str to str, optional
        ``{child: parent}`` sensor names, the root left out: fit only these joints instead of searching
        for the tree.
    root : str, optional
        The sensor to hang the tree from. By default the body that splits the tree most evenly.
    tolerance : float, default 0.005
        Metres: a joint counts as determined once the data pin its centre to within this along every
        direction it needs (docs/design.md §3a).
    slips : bool, default True
        Search for sensor slips and re-fit after them. False fits every frame together, as if no sensor
        had moved on the skin (faster on a long take).

    Returns
    -------
    Calibration
        The fitted skeleton. ``cal.slip_events`` lists the slips found; a joint the take did not move
        enough is in the tree but not determined (``cal.joints.determined``): a take too short or too
        still to fit gives a calibration with no joint determined, not an error.

    Raises
    ------
    TypeError
        `take` is not a take (a path, say: read it with ``flockcal.load_take`` first).
    flockcal.solver.errors.SolverError
        `hierarchy` or `root` names a sensor the take does not have, or the hierarchy is not one tree
        over the take's sensors.

    See Also
    --------
    flockcal.load_take : read a take file.
    flockcal.solver.calibrate : fit an accumulator you fed yourself (live, or merged from several takes).

    Notes
    -----
    A take recorded without tracking the hemisphere (positions read −p while a sensor is outside it) is
    unfolded first, as ``flockcal fit`` unfolds it, with a `UserWarning` saying how many frames were.

    Examples
    --------
    >>> import flockcal
    >>> take, truth = flockcal.simulate(motion="exercise", seconds=20, birds=6, seed=1)
    >>> cal = flockcal.fit(take, root="pelvis")
    >>> cal.parent_map() == truth["parent"]
    True
    >>> bool(cal.joints.determined.all()), cal.slip_events
    (True, ())
    >>> cal.to_dict()["root"]   # the object `flockcal fit --json` prints
    'pelvis'
    """
    from flockcal.takes import ChunkedTake, Take

    if not isinstance(take, ChunkedTake):
        raise TypeError(f"fit takes a Take (flockcal.load_take(path)) or a ChunkedTake, not {type(take).__name__}")
    if isinstance(take, Take):
        # As `flockcal fit` reads a file: a take recorded without tracking the hemisphere unfolded first,
        # said as a warning (the command says it on stderr).
        from flockcal.hemisphere_unfold import unfold_take

        take, how = unfold_take(take)
        if how.frames_unfolded:
            import warnings

            warnings.warn(how.summary(take.names), UserWarning, stacklevel=2)
    calibration = fit_whole_take(take, hierarchy=hierarchy, root=root, tolerance=tolerance)
    return refit_after_slips(take, calibration, tolerance=tolerance)[1] if slips else calibration
