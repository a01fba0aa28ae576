"""The slippage monitor's settings: every threshold, window and switch of `SlipMonitor` in one frozen
`SlipSettings`, checked once when made (docs/slippage.md says what each does to the figures).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from flockcal.solver.slippage.events import SlippageError


@dataclass(frozen=True)
class SlipSettings:
    """How a `SlipMonitor` watches: the defaults are the service's.

    A suspicion (the step test of a joint passing `threshold`) is put to the confirming test from
    `attribute_s` after its onset, again at every step while it is younger than `confirm_s` and not
    clearly refuted, and dropped after that; a confirmed slip is still dropped when the sensor's joints,
    back in a pose of the last `revisit_s`, show the residual they had then (soft tissue comes back), and a
    slip named on a sensor of two or more joints is its leaf neighbour's (a hand's, not the forearm's) where
    its other joints (the elbow) show the residual they had in the same pose. The tests are in units of each joint's own noise,
    measured from the data: `threshold` and `min_evidence` are nats (log-likelihood ratios),
    `min_jump_m` is the smallest step worth reporting and `scale_floor_m` stops exact, noise-free data
    from dividing by zero. A pair whose residual rms exceeds `max_rms_m` is not a joint and is not
    watched. Frames are examined `step_s` at a time, whatever the batches they arrive in. Suspicions
    whose onsets are more than `merge_s` apart are kept and tested apart (`pending`). After an event the
    affected joints re-baseline from the slip time on (they stay quiet for `warmup_s`, at least `lag_s`).
    Where a joint moves into poses its lagged baseline has not seen, the step test and the confirming
    test count `extrapolation_share` of the baseline's own uncertainty as noise: (step test, confirming
    test of a sensor seen through two or more joints, of a sensor seen through one); two values give the
    confirming test one share for both. `reseat_refuted` also moves a suspicion about to be refuted to a
    later start of the likeliest sensor's step (>= `min_jump_m`, likelier than none). Both find more
    slips as the limbs move into new poses and raise false alarms in fresh kiosk guests, so they are off
    by default (docs/slippage.md, "New poses", measures them). `second_look` (shares for a sensor of two
    or more joints, for a leaf) scores a suspicion the default does not confirm again with those shares,
    and reports its slip only where the same pose before the onset shows the step stayed; it raised no
    false alarm in fresh kiosk guests but finds too few more slips to reach issue 32's target, so it is
    off too (same page). `frame_step` (nats, 20 by default; None: off) adds a test that needs no pose model:
    every sensor with a ready joint, at every onset once `frame_step_s` of frames after it have come, is
    scored for a step at that frame, shared by every joint of the sensor in its own frame, against a cubic
    in time and each joint's own rotation over ±`frame_step_s` (`framestep`), its noise at least what each
    joint's speed makes it. A step needs `frame_step` where the step test fired on one of the sensor's
    joints with a start near the onset, and `frame_step_alone` (25; None: never) where it did not. It
    leaves the confirming test's suspicions, quiet times and limits as they are with it off.

    The fields ending in `_shares` and `_nats` are worked out from the others: the three shares of
    `extrapolation_share`, the second look's (1 for the step test, then its two) or None, the frame test's
    threshold (None: off) and the threshold where the step test raised nothing near (inf: never).

    Raises `SlippageError` for windows that contradict each other or shares outside [0, 1].
    """

    min_jump_m: float = 0.01
    warmup_s: float = 5.0
    baseline_s: float = 8.0
    lag_s: float = 1.0
    refresh_s: float = 1.0
    window_s: float = 0.5
    noise_s: float = 0.25
    threshold: float = 25.0
    attribute_s: float = 0.15
    confirm_s: float = 0.8
    step_s: float = 0.1
    min_frames: int = 4
    min_evidence: float = 20.0
    scale_floor_m: float = 2e-4
    max_rms_m: float = 0.05
    revisit_s: float = 40.0
    merge_s: float = 0.05
    extrapolation_share: tuple[float, ...] = (1.0, 1.0, 1.0)
    reseat_refuted: bool = False
    second_look: tuple[float, float] | None = None
    frame_step: float | None = 20.0
    frame_step_s: float = 0.3
    frame_step_alone: float | None = 25.0
    shares: tuple[float, float, float] = field(init=False, repr=False)
    second_look_shares: tuple[float, float, float] | None = field(init=False, repr=False)
    frame_step_nats: float | None = field(init=False, repr=False)
    frame_step_alone_nats: float = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if not self.lag_s > self.window_s:
            raise SlippageError("lag_s must exceed window_s, so a step is never inside its own baseline")
        if not self.confirm_s >= self.attribute_s:
            raise SlippageError("confirm_s must be at least attribute_s: a suspicion is tested from attribute_s to confirm_s")
        share = np.asarray(self.extrapolation_share, dtype=float).ravel()
        if share.shape == (2,):
            share = share[[0, 1, 1]]
        if share.shape != (3,) or not ((share >= 0) & (share <= 1)).all():
            raise SlippageError("extrapolation_share is (step test, confirming test of a sensor with two or more "
                                f"joints, of a sensor with one), each within [0, 1]: {self.extrapolation_share!r}")
        frame_step = None if self.frame_step is None or not self.frame_step > 0 else float(self.frame_step)
        if self.second_look is None or len(self.second_look) == 0:
            second = None
        else:
            look = np.asarray(self.second_look, dtype=float).ravel()
            if look.shape != (2,) or not ((look >= 0) & (look <= 1)).all():
                raise SlippageError("second_look is (share for a sensor with two or more joints, for a sensor with "
                                    f"one), each within [0, 1], or None: {self.second_look!r}")
            second = (1.0, float(look[0]), float(look[1]))
        derived = {
            "shares": tuple(float(x) for x in share),
            "second_look_shares": second,
            "frame_step_nats": frame_step,
            # Where the step test raised nothing near an onset, a frame step needs this much (inf: none there).
            "frame_step_alone_nats": (np.inf if frame_step is None or self.frame_step_alone is None
                                      else max(float(self.frame_step_alone), frame_step)),
            "min_jump_m": float(self.min_jump_m),
            "min_frames": int(self.min_frames),
            "reseat_refuted": bool(self.reseat_refuted),
        }
        for name, value in derived.items():
            object.__setattr__(self, name, value)
