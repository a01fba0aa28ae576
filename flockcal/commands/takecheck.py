"""Whether a take holds enough to be fitted: too short (too few frames or seconds) or too still (no joint
of the fitted tree determined). The commands that fit a take print a one-line warning and stop with
exit code 3 unless given --allow-partial.
"""

from __future__ import annotations

import sys

import numpy as np

# Fewer than these and no joint can have turned enough to be located. 20 frames already give each
# pair's 6 unknowns 54 spare equations; one second is the shortest a person takes to swing a limb.
MIN_FRAMES = 20
MIN_SECONDS = 1.0
PARTIAL_EXIT = 3  # the take was read but is not worth fitting (2 is bad input)


def add_option(parser) -> None:
    parser.add_argument("--allow-partial", action="store_true",
                        help="fit a take that is too short or too still anyway (it still gets the warning, "
                             "but exits 0)")


def determined_joints(cal) -> np.ndarray:
    """Which joints of the fitted tree are determined (docs/design.md §3a), one bool per `cal.joints` entry:
    the solver's own decision, so the warning, the table and the JSON never disagree."""
    return np.asarray(cal.joints.determined, dtype=bool)


def too_short(take) -> str | None:
    """Why `take` (a Take, or a take file read a chunk at a time) is too short to fit, or None."""
    from flockcal.frames import chunk_frames, frames_of

    both, first, last = 0, 0.0, 0.0
    for k, f in enumerate(frames_of(take, chunk_frames(len(take.names)))):
        both += np.count_nonzero(f.valid.sum(axis=1) >= 2)  # frames with at least one pair of valid sensors
        first = float(f.times[0]) if k == 0 else first
        last = float(f.times[-1])
    span = last - first if take.n_frames > 1 else 0.0
    if both >= MIN_FRAMES and span >= MIN_SECONDS:
        return None
    return (f"too short to fit: {both} frame(s) with two sensors valid over {span:.2f} s (a fit needs at least "
            f"{MIN_FRAMES} frames and {MIN_SECONDS:g} s) — record a longer take")


def too_still(cal) -> str | None:
    """Why the calibration `cal` of a take fitted nothing, or None."""
    if determined_joints(cal).any():
        return None
    joints = len(cal.joints)
    what = (f"none of the {joints} joint(s) of the fitted tree is determined (none turned enough to pin its "
            "centre)" if joints else
            "no two sensors turned relative to each other (they moved as one rigid body)")
    return f"too still to fit: {what} — record the performer moving each joint"


def stop_for(command: str, source: str, problem: str | None, allow_partial: bool) -> bool:
    """Print the one-line warning for `problem` (if any); True when the command must stop (exit 3)."""
    if problem is None:
        return False
    advice = "fitting it anyway (--allow-partial)" if allow_partial else "pass --allow-partial to fit it anyway"
    print(f"flockcal {command}: warning: {source} is {problem}; {advice}", file=sys.stderr)
    return not allow_partial
