"""Sensor slippage and swap detection (docs/design.md §4): a live `SlipMonitor` fed the same micro-batches as
the accumulator plus the current joint estimates, and `detect_slips` for a recorded take.

Per joint, a window-limited GLR test for a step in the residual vector (seen from either sensor of the
joint, against that joint's own baseline, weighted by the noise the data shows) raises a suspicion;
`attribution` then asks whether a step at that moment is needed at all once each joint's
residual is fitted as a smooth function of the configuration (soft tissue is one, a slip is not), and
names the sensor whose joints all stepped (or the pair that swapped); `revisit` lets the same
pose seen before overrule it. Only then is an event reported.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, replace

import numpy as np

from flockcal.errors import FlockcalError
from flockcal.frames import frames_of
from flockcal.solver.slippage.attribution import CANDIDATE_SHARE, Attribution, Window, attribute
from flockcal.solver.slippage.buffer import FrameBuffer
from flockcal.solver.slippage.framestep import FrameStep, frame_steps, noise_law, step_contrast
from flockcal.solver.slippage.baseline import SmoothBaseline, neighbours, smooth_baseline
from flockcal.solver.slippage.pending import PendingSuspicions, Suspicion
from flockcal.solver.slippage.revisit import CAME_BACK_NATS, PoseHistory, came_back
from flockcal.solver.slippage.stats import (best_step, glr_candidates, joint_geometry, local_variance, present, residual,
                                            touching)


class SlippageError(FlockcalError, ValueError):
    """Inputs the slippage monitor cannot use (shapes, names, a calibration without joints)."""


@dataclass(frozen=True)
class SlipEvent:
    """One sensor moved on the body: when, which (with the alternatives), which joints, how far."""

    time_s: float  # estimated time of the slip (first frame of the step)
    sensor: str
    candidates: tuple[str, ...]  # sensors that could explain it, most likely first
    confidence: float  # posterior share of `sensor`
    joints: tuple[str, ...]  # the affected joints, each named by its child body
    jump_mm: float  # size of the residual step
    detected_s: float = float("nan")  # time of the frame at which the monitor reported it
    sensor_index: int = -1
    joint_indices: tuple[int, ...] = ()

    kind = "slip"

    def to_dict(self) -> dict:
        """The `slip_events` entry of docs/design.md §5 (extended with kind, confidence and detected_s)."""
        return {"kind": "slip", "time_s": round(self.time_s, 4), "sensor": self.sensor,
                "candidates": list(self.candidates), "confidence": round(self.confidence, 4),
                "joints": list(self.joints), "jump_mm": round(self.jump_mm, 2),
                "detected_s": round(self.detected_s, 4)}


@dataclass(frozen=True)
class SwapEvent:
    """Two sensors exchanged identity (their data streams swapped) from `time_s` on."""

    time_s: float
    a: str
    b: str
    joints: tuple[str, ...]
    jump_mm: float
    confidence: float = 1.0
    detected_s: float = float("nan")
    sensor_indices: tuple[int, int] = (-1, -1)
    joint_indices: tuple[int, ...] = ()

    kind = "swap"

    @property
    def sensor(self) -> str:
        return self.a

    @property
    def candidates(self) -> tuple[str, ...]:
        return (self.a, self.b)

    def to_dict(self) -> dict:
        """A `slip_events` entry of kind "swap": `sensor` and `candidates` name both sensors."""
        return {"kind": "swap", "time_s": round(self.time_s, 4), "sensor": self.a,
                "candidates": [self.a, self.b], "sensors": [self.a, self.b],
                "confidence": round(self.confidence, 4), "joints": list(self.joints),
                "jump_mm": round(self.jump_mm, 2), "detected_s": round(self.detected_s, 4)}


class SlipMonitor:
    """Live slippage detector over the p joints of a tree (or any joint list).

    joints: (p, 2) sensor indices (child, parent). Feed `add_frames` every batch of frames with the current
    joint estimates c, l (p, 3) (the child and parent frame coordinates of each joint centre); it returns
    the events confirmed in this batch. After an event the affected joints re-baseline from the slip
    time on (they stay quiet for `warmup_s`, at least `lag_s`); the others keep their state.

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
    whose onsets are more than `merge_s` apart are kept and tested apart (`pending`).
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
    """

    def __init__(self, joints, n_sensors: int, rate_hz: float, names=None, *,
                 min_jump_m: float = 0.01, warmup_s: float = 5.0, baseline_s: float = 8.0,
                 lag_s: float = 1.0, refresh_s: float = 1.0, window_s: float = 0.5, noise_s: float = 0.25,
                 threshold: float = 25.0, attribute_s: float = 0.15, confirm_s: float = 0.8,
                 step_s: float = 0.1, min_frames: int = 4, min_evidence: float = 20.0,
                 scale_floor_m: float = 2e-4, max_rms_m: float = 0.05, revisit_s: float = 40.0,
                 merge_s: float = 0.05, extrapolation_share: tuple[float, ...] = (1.0, 1.0, 1.0),
                 reseat_refuted: bool = False, second_look: tuple[float, float] | None = None,
                 frame_step: float | None = 20.0, frame_step_s: float = 0.3, frame_step_alone: float | None = 25.0):
        J = _checked_joints(joints, n_sensors)
        if not rate_hz > 0:
            raise SlippageError(f"rate_hz must be positive, got {rate_hz!r}")
        if not lag_s > window_s:
            raise SlippageError("lag_s must exceed window_s, so a step is never inside its own baseline")
        if not confirm_s >= attribute_s:
            raise SlippageError("confirm_s must be at least attribute_s: a suspicion is tested from attribute_s to confirm_s")
        share = np.asarray(extrapolation_share, dtype=float).ravel()
        if share.shape == (2,):
            share = share[[0, 1, 1]]
        if share.shape != (3,) or not ((share >= 0) & (share <= 1)).all():
            raise SlippageError("extrapolation_share is (step test, confirming test of a sensor with two or more "
                                f"joints, of a sensor with one), each within [0, 1]: {extrapolation_share!r}")
        self.extrapolation_share = tuple(float(x) for x in share)
        self.frame_step = None if frame_step is None or not frame_step > 0 else float(frame_step)
        self._half = max(4, int(round(frame_step_s * rate_hz)))
        self._contrast = step_contrast(self._half)
        # A step the scan finds this close to the newest onset it can test waits for the onsets just after it:
        # a neighbour's best may lie there.
        self._scan_hold = max(1, int(round(merge_s * rate_hz)))
        # The scan looks every other step (0.2 s of onsets at once): its cost is mostly per look, and a slip
        # it finds is then reported 0.3-0.5 s after its onset rather than 0.3-0.4 s.
        self._scan_every = 2 * max(1, int(round(step_s * rate_hz)))
        self._scanned = -1  # global frame index: the frame scan has tested every onset before it
        # Where the step test raised nothing near an onset, a frame step needs this much (None: none there).
        self.frame_step_alone = (np.inf if self.frame_step is None or frame_step_alone is None
                                 else max(float(frame_step_alone), self.frame_step))
        # The step test's hits, (global start frame, joint), while the frame scan may still test onsets near them.
        self._hits: deque = deque()
        # An onset is near a hit whose start is up to 0.3 s before it or 0.1 s after: the frames the frame test
        # looked at around a suspicion before the scan (a slip's own joints often cross the threshold 0.1-0.3 s
        # after its neighbours' soft tissue has).
        self._near = (int(round(0.3 * rate_hz)), int(round(0.1 * rate_hz)))
        self.frame_steps = 0  # slips confirmed by the frame-rate step test where the default did not
        # The frame scan's best step of each sensor per look: (onset time, sensor, score, evidence,
        # disagreement, jump m).
        self.frame_log: deque = deque(maxlen=2000)
        self._law: tuple | None = None  # (frame index, joints, (a, b)): the frame test's noise law, see _noise_law
        self.reseat_refuted = bool(reseat_refuted)
        if second_look is None or len(second_look) == 0:
            self.second_look = None
        else:
            look = np.asarray(second_look, dtype=float).ravel()
            if look.shape != (2,) or not ((look >= 0) & (look <= 1)).all():
                raise SlippageError("second_look is (share for a sensor with two or more joints, for a sensor with "
                                    f"one), each within [0, 1], or None: {second_look!r}")
            self.second_look = (1.0, float(look[0]), float(look[1]))
        self.joints = J
        self.m = int(n_sensors)
        self.rate_hz = float(rate_hz)
        self.names = tuple(str(x) for x in names) if names is not None else tuple(str(i) for i in range(self.m))
        if len(self.names) != self.m:
            raise SlippageError(f"{len(self.names)} names given for {self.m} sensors")
        self.min_jump = float(min_jump_m)
        self.warmup_s, self.baseline_s, self.lag_s, self.refresh_s = warmup_s, baseline_s, lag_s, refresh_s
        self.window = max(2, int(round(window_s * rate_hz)))
        self.noise_frames = max(5, int(round(noise_s * rate_hz)))
        self.threshold, self.attribute_s, self.confirm_s, self.step_s = threshold, attribute_s, confirm_s, step_s
        self.min_frames = int(min_frames)
        self.min_evidence, self.scale_floor, self.max_rms = min_evidence, scale_floor_m, max_rms_m
        self._nbrs = neighbours(J)
        p = len(J)
        self._baseline_frames = int(round(baseline_s * rate_hz))
        # Frames kept by the fits, evenly spread over their window: the smooth part needs no more.
        self._fit_rows = 300
        cap = int(np.ceil((baseline_s + lag_s + 1.0) * rate_hz))
        self._buf = FrameBuffer(cap, self.m, J)
        # Poses of the last revisit_s at about 50 Hz, to see whether the residual came back with the pose.
        self._history = PoseHistory(J, self.m, rate_hz, revisit_s, every=int(round(rate_hz / 50.0)))
        self.came_back = 0  # suspected slips that the same pose before showed to be soft tissue
        self.renamed = 0  # slips named on a leaf's neighbour that the same pose before gave to the leaf
        self.reseated = 0  # suspicions moved to a slip's later start before being confirmed
        self._chunk = max(1, int(round(step_s * rate_hz)))
        self.segment_start = np.full(p, np.nan)  # time each joint's current segment began
        self._t0 = np.nan  # time of the first frame seen
        self._fed = False
        self.ready = np.zeros(p, dtype=bool)
        self.rms = np.full(p, np.nan)  # each joint's residual rms over its baseline window, metres
        self.base: SmoothBaseline | None = None
        self._c_ref = np.full((p, 3), np.nan)
        self._l_ref = np.full((p, 3), np.nan)
        self._last_refresh = -np.inf
        self._fresh: tuple[int, int] | None = None  # global frames whose buf.dx/dy/w follow the current baseline
        self._quiet = np.full(p, -1, dtype=np.int64)  # global frame index: no step may start before it
        self._pending = PendingSuspicions(p, int(round(merge_s * rate_hz)))
        self.score = np.zeros(p)  # latest GLR score per joint (nats), for display
        self.confirmations = 0  # suspicions put to the confirming test (for benchmarks)
        self.events: list[SlipEvent | SwapEvent] = []

    # -- public -------------------------------------------------------------------------------------
    def add_frames(self, times, rotations, positions, valid=None, c=None, l=None) -> list:
        """Take a batch of frames and the current joint estimates; return the events confirmed now."""
        ts, R, t, v = self._frames(times, rotations, positions, valid)
        n = len(ts)
        p = len(self.joints)
        if c is None or l is None:
            raise SlippageError("add_frames needs the current joint estimates c and l, each (p, 3)")
        c = np.asarray(c, dtype=float).reshape(p, 3)
        l = np.asarray(l, dtype=float).reshape(p, 3)
        self._begin(ts)
        self._fed = True
        finite = np.isfinite(c).all(axis=1) & np.isfinite(l).all(axis=1)
        c, l = np.where(finite[:, None], c, 0.0), np.where(finite[:, None], l, 0.0)
        out = []
        a = 0
        while a < n:
            ends = self._plan(ts, a)
            out += self._block(ts, R, t, v, a, ends, c, l, finite)
            a = ends[-1]
        self.events += out
        return out

    def prime(self, times, rotations, positions, valid=None) -> None:
        """Take frames that came before the watch began (the session's first seconds, before there was a
        tree): they fill the baselines' window and the pose history, and are not tested for steps. The
        next `add_frames` continues from them. Nothing to do once `add_frames` has run."""
        if self._fed:
            raise SlippageError("prime takes the frames before the first add_frames, not after it")
        ts, R, t, v = self._frames(times, rotations, positions, valid)
        for a in range(0, len(ts), self._buf.capacity):
            sl = slice(a, a + self._buf.capacity)
            self._begin(ts[sl])
            g0 = self._buf.append(ts[sl], R[sl], t[sl], v[sl])
            new = self._buf.since(g0)
            buf = self._buf
            self._history.append(g0, buf.times[new], buf.R[new], buf.t[new], buf.valid[new], buf.g[new],
                                 buf.Q[new], buf.pv[new])

    def rejoint(self, joints) -> None:
        """Watch another joint list (a changed tree) from now on, without warming up again.

        The frames and poses seen stay, and each joint in both lists (the same child and parent) keeps
        its state: its segment, what its step test has already looked at, a suspicion pending on it, its
        events. A joint new to the list is worked out from the frames kept: its segment began at the
        latest event of either of its sensors (or the first frame), so it is watched as soon as the
        baseline window holds enough of it, at the next baseline refresh."""
        J = _checked_joints(joints, self.m)
        index = {tuple(r): k for k, r in enumerate(self.joints.tolist())}
        keep = np.array([index.get(tuple(r), -1) for r in J.tolist()], dtype=int)
        kept = keep >= 0
        k = np.maximum(keep, 0)
        p = len(J)
        start = np.full(p, self._t0)
        for ev in self.events:
            touched = touching(J, [ev.sensor_index] if ev.kind == "slip" else list(ev.sensor_indices))
            start = np.where(touched, np.fmax(start, ev.time_s), start)
        self.segment_start = np.where(kept, self.segment_start[k], start)
        self._quiet = np.where(kept, self._quiet[k], -1)
        self.score = np.where(kept, self.score[k], 0.0)
        self.rms = np.where(kept, self.rms[k], np.nan)
        self.ready = np.zeros(p, dtype=bool)  # the next block refreshes every baseline on the new list
        self._pending.rejoint(keep, kept)
        renum = {int(old): new for new, old in enumerate(keep.tolist()) if old >= 0}
        self._hits = deque((st, renum[q]) for st, q in self._hits if q in renum)
        self.joints = J
        self._nbrs = neighbours(J)
        self._buf = self._buf.rejoint(J)
        self._history.rejoint(J)
        self.base = None
        self._c_ref = np.full((p, 3), np.nan)
        self._l_ref = np.full((p, 3), np.nan)
        self._last_refresh = -np.inf
        self._fresh = None

    def status(self) -> dict:
        """Per joint (by child name): watching yet, latest step evidence (nats) and the current
        segment's start, plus every event so far, for a status page."""
        joints = {
            self.names[int(c)]: {"ready": bool(r), "score": round(float(sc), 2), "segment_start_s": None if st != st else float(st),
                                 "rms_mm": None if rms != rms else round(1000.0 * float(rms), 2),
                                 "joined": not rms > self.max_rms}
            for (c, _), r, sc, st, rms in zip(self.joints, self.ready, self.score, self.segment_start, self.rms)
        }
        return {"joints": joints, "threshold": self.threshold, "events": [e.to_dict() for e in self.events]}

    # -- internals ----------------------------------------------------------------------------------
    def _frames(self, times, rotations, positions, valid):
        """Frames as (times (n,), R (n, m, 3, 3), t (n, m, 3), valid (n, m)); non-finite poses invalid and zeroed."""
        R = np.asarray(rotations, dtype=float)
        t = np.asarray(positions, dtype=float)
        if R.ndim == 3:
            R, t = R[None], t[None]
        n = R.shape[0]
        if R.shape != (n, self.m, 3, 3) or t.shape != (n, self.m, 3):
            raise SlippageError(f"frames must be rotations (n, {self.m}, 3, 3) and positions (n, {self.m}, 3); "
                                f"got {R.shape} and {t.shape}")
        ts = np.atleast_1d(np.asarray(times, dtype=float))
        if ts.shape != (n,):
            raise SlippageError(f"times must have shape ({n},), got {ts.shape}")
        v = np.ones((n, self.m), dtype=bool) if valid is None else np.asarray(valid, dtype=bool).reshape(n, self.m)
        v = v & np.isfinite(R).all(axis=(2, 3)) & np.isfinite(t).all(axis=2)
        return ts, np.where(v[..., None, None], R, 0.0), np.where(v[..., None], t, 0.0), v

    def _begin(self, ts: np.ndarray) -> None:
        """The first frames ever seen start every joint's first segment."""
        if len(ts) and not np.isfinite(self._t0):
            self._t0 = float(ts[0])
            self.segment_start[np.isnan(self.segment_start)] = ts[0]

    def _plan(self, ts: np.ndarray, a: int) -> list[int]:
        """Ends (exclusive) of the steps of `step_s` from frame a that can be examined together: the
        first, and those after it that need no new baseline (the step test of all of them is then one
        computation; a step still runs its suspicion logic on its own, in order)."""
        n = len(ts)
        ends = [min(n, a + self._chunk)]
        due = ts[ends[0] - 1] - self._last_refresh >= self.refresh_s or self.base is None
        last = ts[ends[0] - 1] if due else self._last_refresh
        limit = a + int(round(self.refresh_s * self.rate_hz)) + self._chunk
        while ends[-1] < min(n, limit):
            nxt = min(n, ends[-1] + self._chunk)
            if ts[nxt - 1] - last >= self.refresh_s:
                break
            ends.append(nxt)
        return ends

    def _block(self, ts, R, t, v, a: int, ends: list[int], c, l, finite) -> list:
        buf = self._buf
        g0 = buf.append(ts[a:ends[-1]], R[a:ends[-1]], t[a:ends[-1]], v[a:ends[-1]])
        new = buf.since(g0)
        self._history.append(g0, buf.times[new], buf.R[new], buf.t[new], buf.valid[new], buf.g[new], buf.Q[new],
                             buf.pv[new])
        step_last = [g0 + e - a - 1 for e in ends]  # global index of each step's last frame
        now = float(ts[ends[0] - 1])
        if now - self._last_refresh >= self.refresh_s or self.base is None:
            self._refresh(now, c, l)
        else:
            # New estimates change every residual by δc − Q δl, which the baseline's form follows
            # exactly: shift it instead of recomputing (the deviations do not change at all).
            self.base.shift(c - self._c_ref, l - self._l_ref)
            self._c_ref, self._l_ref = c.copy(), l.copy()
        # The step test's window plus the frames the local noise level needs, before the first step.
        first = g0 - (self.window + self.noise_frames)
        self._deviations(first, c, l)
        ready = self.ready & finite
        out: list = []
        j = 0
        candidates = None
        while j < len(ends):
            if not self._pending and not ready.any():
                break
            candidates = candidates or self._candidates(first, step_last)
            score, start, first_row = self._scan(candidates, j, ready)
            hit = score >= self.threshold  # (steps j…, p)
            for k in range(j, len(ends)):
                self.score = score[k - j]
                self._pending.add(hit[k - j], first_row + start[k - j])
                if self.frame_step is not None:
                    self._hits.extend((int(first_row + start[k - j, q]), q) for q in np.flatnonzero(hit[k - j]))
                now = float(ts[ends[k] - 1])
                changed, ev = self._suspicions(now, step_last[k], ready, c, l) if self._pending else (False, [])
                if self.frame_step is not None:
                    found = self._frame_scan(now, step_last[k], self.ready & finite, c, l)
                    changed, ev = changed or bool(found), ev + found
                out += ev
                if changed:  # the quiet times or the joints' state moved: test the rest afresh
                    break
            else:
                break
            ready = self.ready & finite
            j = k + 1
        return out

    def _candidates(self, first: int, lasts: list[int]):
        """The step test's evidence at the last frames `lasts` of a block's steps, for every candidate start
        (`glr_candidates`): the block's deviations stay as they are while its steps are tested, so one
        computation serves every round of them; `_scan` picks each round's best."""
        buf = self._buf
        sl = slice(buf.slot(first), buf.slot(lasts[-1]) + 1)
        first_row = buf.index_of(sl.start)
        xs = np.concatenate([buf.dx[sl], buf.dy[sl]], axis=1)  # child-frame and parent-frame series side by side
        w = buf.w[sl]
        ws = np.concatenate([w, w], axis=1)
        # One end per step, its last frame: a step that stays only gains evidence with time.
        g, usable, tau = glr_candidates(xs, ws, np.asarray(lasts) - first_row, self.window, 0.5 * self.min_jump,
                                        self.min_frames)
        return g, usable, tau, first_row

    def _scan(self, candidates, j: int, ready):
        """The step test at the block's steps from the j-th on: scores and starts (steps, p)."""
        g, usable, tau, first_row = candidates
        earliest = np.maximum(self._quiet, 0) - first_row
        score, start = best_step(g[j:], usable[j:], tau[j:], np.concatenate([earliest, earliest]))
        p = len(self.joints)
        which = score[:, p:] > score[:, :p]
        score = np.where(which, score[:, p:], score[:, :p])
        start = np.where(which, start[:, p:], start[:, :p])
        return np.where(ready[None, :], score, 0.0), start, first_row

    def _suspicions(self, now: float, last: int, ready, c, l) -> tuple[bool, list]:
        """Put every pending suspicion that is due to the confirming test, oldest onset first, on the
        frames up to global index `last`. Returns (whether the quiet times or joint states changed, the events)."""
        changed, out = False, []
        for item in list(self._pending.items):
            if item in self._pending.items:  # (an event before it may have taken all its joints)
                moved, ev = self._suspicion(item, now, last, ready & self.ready, c, l)
                changed, out = changed or moved, out + ev
        return changed, out

    def _suspicion(self, item: Suspicion, now: float, last: int, ready, c, l) -> tuple[bool, list]:
        buf = self._buf
        onset, fired = item.onset, item.fired
        t_onset = float(buf.times[buf.slot(onset)])
        age = now - t_onset
        if age < self.attribute_s or now < item.next_try:
            return False, []  # gather a little more evidence before naming the sensor
        self.confirmations += 1
        more_looks = age + self.step_s <= self.confirm_s + 1e-9
        look = self.second_look is not None
        # With the second look, what the first round's test decides stays as it was, except that a suspicion
        # re-seated from a refuted onset (below) must show the same verdict as the second look's slips.
        att, later = self._attribute(onset, fired, ready, c, l, last, more_looks,
                                     reseat=False if look else None, verify=item.verify)
        if att.kind is None and later is None and look:
            # The second look: scored counting `second_look` of the lagged baseline's extrapolation as noise
            # (none, as the limbs move into a new pose, where it is most of it); a slip it names stands only
            # where the same pose before the onset shows the step stayed (`_attribute`).
            second, later = self._attribute(onset, fired, ready, c, l, last, more_looks, share=self.second_look,
                                            verify=True)
            if later is not None:
                item.verify = True
            if second.kind == "slip" and later is None:
                att = second
            else:
                att = Attribution(None, evidence=max(att.evidence, second.evidence))
        if later is not None:
            # The step this suspicion would confirm starts well after its onset: a slip landed inside the
            # window of a suspicion kept for another look. Test it again at the step's own start.
            item.onset = later
            item.next_try = now + self.step_s - 0.5 / self.rate_hz
            self._pending.items.sort(key=lambda x: x.onset)
            self.reseated += 1
            return False, []
        if att.kind is None:
            if more_looks and att.evidence > 0:
                # A step is likelier than not, but not yet by the margin: look again one step later.
                item.next_try = now + self.step_s - 0.5 / self.rate_hz
                return False, []
            self._pending.judged(item, last, self._quiet)
            return True, []
        self._pending.judged(item, last, self._quiet)
        return True, [self._report(att, onset, t_onset, now)]

    def _report(self, att: Attribution, onset: int, t_onset: float, now: float):
        """The event of a confirmed attribution: its joints start a new segment from the onset."""
        affected = np.asarray(att.joints, dtype=int)
        names = tuple(self.names[int(self.joints[j, 0])] for j in affected)
        if att.kind == "slip":
            ev = SlipEvent(t_onset, self.names[att.sensor], tuple(self.names[k] for k, _ in att.candidates),
                           att.confidence, names, 1000.0 * att.jump_m, now, att.sensor, tuple(affected.tolist()))
        else:
            ev = SwapEvent(t_onset, self.names[att.sensor], self.names[att.other], names, 1000.0 * att.jump_m,
                           att.confidence, now, (att.sensor, att.other), tuple(affected.tolist()))
        self.segment_start[affected] = t_onset
        self.ready[affected] = False
        # Its joints the event does not re-baseline (soft tissue that fired with it) are quieted as a
        # refutation's are (by the caller); other suspicions on the re-baselined joints are void: their
        # baseline is gone.
        self._quiet[affected] = onset
        gone = np.zeros(len(self.joints), dtype=bool)
        gone[affected] = True
        self._pending.forget(gone)
        return ev

    def _frame_scan(self, now: float, last: int, ready, c, l) -> list:
        """The frame-rate step test, every other step, at every onset it can now see (up to `frame_step_s`
        before global frame `last`) and every sensor with a ready joint: a slip it finds there is reported at
        once, whatever the other tests made of it. Its windows never reach back past a joint's latest event."""
        buf = self._buf
        h = self._half
        hi_g = last - h + 2
        # Onsets older than a look or so are not gone back to (the joints were not ready then, or the frames
        # went by while nothing was watched).
        lo_g = max(self._scanned, buf.first_index + h, hi_g - self._scan_every - self._chunk - self._scan_hold)
        out: list = []
        if not ready.any():
            self._scanned = max(self._scanned, hi_g)
            return out
        if hi_g - lo_g < self._scan_every:
            return out
        rows = slice(buf.slot(lo_g - h), buf.slot(last) + 1)
        base = buf.index_of(rows.start)
        pv = buf.pv[rows] & (buf.times[rows][:, None] >= self.segment_start[None, :])  # as the other tests mask
        law = self._noise_law(c, l)
        sensors = present(self.joints[ready])
        while self._hits and self._hits[0][0] < lo_g - self._near[0]:
            self._hits.popleft()  # (hits come in order of the steps that found them, near enough in start)
        while True:
            found = frame_steps(buf.g[rows], buf.Q[rows], pv, c, l, self.joints, sensors, ready, lo_g - base,
                                hi_g - base, h, self.scale_floor, self._contrast, buf.t[rows], law)
            if not out:
                for f in found:
                    self.frame_log.append((float(buf.times[rows.start + f.onset]), self.names[f.sensor], f.score,
                                           f.evidence, f.disagreement, float(np.linalg.norm(f.step))))
            # A sensor seen through one joint cannot tell its own step from its neighbour's across that joint when
            # the joint hardly turns (and a fast-turning joint's skin blurs the difference): where the neighbour's
            # other joints show a step of their own at the same onset, it is the neighbour's. Two such tests
            # passing the frame test at one onset are evidence enough where no step-test hit is near.
            neighbour: dict[int, FrameStep | None] = {}
            good = []
            for f in found:
                if np.linalg.norm(f.step) < self.min_jump or f.score < self.frame_step:
                    continue
                if len(f.joints) == 1:
                    neighbour[id(f)] = self._neighbour_step(f, rows, pv, c, l, ready, law)
                if f.score >= self._needed(f.sensor, base + f.onset) or neighbour.get(id(f)) is not None:
                    good.append(f)
            if not good:
                break
            best = max(good, key=lambda f: f.score)
            if base + best.onset >= hi_g - self._scan_hold and not out:
                # A neighbour's step at the frames just after may explain it better: decide next look.
                self._scanned = max(lo_g, base + best.onset - self._scan_hold)
                return out
            J = self.joints
            cands = [(best.sensor, 1.0)] + [(f.sensor, 0.0) for f in good if f is not best]
            other = neighbour.get(id(best))
            if other is not None:
                cands = [(other.sensor, 1.0), (best.sensor, 0.0)] + cands[1:]
                best = replace(best, sensor=other.sensor, step=other.step, score=other.score)
            mine = np.flatnonzero((J[:, 0] == best.sensor) | (J[:, 1] == best.sensor))
            self.frame_steps += 1
            att = Attribution("slip", best.sensor, -1, cands, 1.0, mine.tolist(), float(np.linalg.norm(best.step)),
                              best.score, best.step)
            onset = base + best.onset
            out.append(self._report(att, onset, float(buf.times[buf.slot(onset)]), now))
            ready = ready & self.ready
            sensors = present(self.joints[ready])
            if not len(sensors):
                break
        self._scanned = hi_g
        return out

    def _needed(self, sensor: int, onset: int) -> float:
        """The evidence a frame step needs: `frame_step` where the step test has fired on one of the sensor's
        joints with a start near its onset (the step test's suspicion, as before the scan), else
        `frame_step_alone`: every sensor at every onset is many more tries, and the hour soaks' highest scores
        where nothing slipped came from those."""
        if self.frame_step_alone <= self.frame_step:
            return self.frame_step
        back, ahead = self._near
        J = self.joints
        for start, q in self._hits:
            if onset - back <= start <= onset + ahead and (J[q, 0] == sensor or J[q, 1] == sensor):
                return self.frame_step
        return self.frame_step_alone

    def _neighbour_step(self, leaf, rows: slice, pv, c, l, ready, law):
        """The frame step of the sensor across a one-joint sensor's joint, on its other ready joints alone,
        within `merge_s` of the leaf's onset: returned when it passes the frame test itself, else None."""
        j = int(leaf.joints[0])
        nb = self._across(j, leaf.sensor)
        own = ready & ((self.joints[:, 0] == nb) | (self.joints[:, 1] == nb))
        own[j] = False
        if not own.any():
            return None
        buf = self._buf
        h = self._scan_hold
        found = frame_steps(buf.g[rows], buf.Q[rows], pv, c, l, self.joints, [nb], own, leaf.onset - h,
                            leaf.onset + h + 1, self._half, self.scale_floor, self._contrast, buf.t[rows], law)
        if found and found[0].score >= self.frame_step and np.linalg.norm(found[0].step) >= self.min_jump:
            return found[0]
        return None

    def _across(self, j: int, s: int) -> int:
        """The sensor at the other end of joint j from sensor s."""
        return int(self.joints[j, 1] if self.joints[j, 0] == s else self.joints[j, 0])

    def _noise_law(self, c, l) -> tuple[np.ndarray, np.ndarray]:
        """Each joint's noise against its speed over the stored frames (`framestep.noise_law`, ten seconds or
        so: enough fast and slow frames to tell the two apart), worked out again once a second of new frames
        has come or the joints changed: a tracker's noise law changes slowly."""
        buf = self._buf
        end = buf.index_of(buf.hi)
        if self._law is None or self._law[1] is not self.joints or end - self._law[0] >= self.rate_hz:
            sl = slice(buf.lo, buf.hi)
            self._law = (end, self.joints, noise_law(buf.g[sl], buf.Q[sl], buf.t[sl], buf.pv[sl], c, l, self.joints))
        return self._law[2]

    def _deviations(self, first: int, c, l) -> None:
        """Bring the buffer's deviations and noise weights up to date from global frame `first` on.
        Only frames not yet worked out against the current baseline are (the others cannot change: the
        baseline follows new estimates exactly), with the noise window they need behind them."""
        buf = self._buf
        end = buf.index_of(buf.hi)
        if self._fresh is None or self._fresh[0] > first:
            new_from, var_from = first, first
        else:
            new_from = self._fresh[1]
            var_from = max(self._fresh[0], new_from - self.noise_frames - 1)
        if new_from >= end:
            return
        sl, rows = buf.since(new_from), buf.since(var_from)
        Q = buf.Q[sl]
        buf.dx[sl], buf.dy[sl] = self.base.deviations(residual(buf.g[sl], Q, c, l), Q)
        var = local_variance(buf.dx[rows], buf.pv[rows], self.noise_frames)[sl.start - rows.start:]
        sigma2 = np.nan_to_num(self.base.sigma, nan=0.0) ** 2
        floor = np.maximum(0.25 * sigma2, self.scale_floor**2)
        ok = np.isfinite(var)
        var = np.maximum(np.where(ok, var, 1.0), floor)
        # Where the configuration is new the baseline extrapolates: the step test, which measures against
        # it, counts its uncertainty as noise. The confirming test fits its own smooth function over the
        # window; for a sensor seen through two or more joints, which a slip moves by one vector in its own
        # frame while skin in a new pose moves each joint its own way, it may count less of it
        # (`extrapolation_share`). By default it counts all of it: counting none raised false alarms in
        # fresh kiosk guests, for leaves and for sensors of two joints alike (docs/slippage.md).
        extra = sigma2 * self.base.leverage(Q)
        live = buf.pv[sl] & ok
        step_share, joined_share = self.extrapolation_share[:2]
        buf.w[sl] = np.where(live, 1.0 / (var + step_share * extra), 0.0)
        buf.nv[sl] = np.where(live, var, 0.0)
        if joined_share != step_share:
            buf.wc[sl] = np.where(live, 1.0 / (var + joined_share * extra), 0.0)
        self._fresh = (min(first, new_from) if self._fresh is None else min(self._fresh[0], new_from), end)

    def _attribute(self, onset: int, fired: np.ndarray, ready: np.ndarray, c, l, last: int, more_looks: bool = False,
                   share: tuple | None = None, reseat: bool | None = None, verify: bool = False):
        """Put the suspicion to the confirming test on the window from `baseline_s` before the onset
        to global frame `last`. Returns the attribution and, when the slip it names starts well after
        the onset, that start (global frame; else None). `share` (step test, sensor of two or more joints,
        leaf): the extrapolation counted instead of `extrapolation_share`'s; `reseat`: instead of
        `reseat_refuted`; `verify`: a slip stands only where the same pose before shows the step stayed."""
        buf = self._buf
        full = slice(buf.slot(onset - self._baseline_frames), buf.slot(last) + 1)
        onset_row = buf.slot(onset) - full.start
        # The frames long before the onset only pin the smooth part of the fit: every stride-th of them,
        # each standing for stride frames, does that at a fraction of the cost.
        cut = max(onset_row - self.window, 0)
        stride = max(1, cut // self._fit_rows)
        rows = np.concatenate([np.arange(cut % stride, cut, stride), np.arange(cut, full.stop - full.start)]) + full.start
        times = buf.times[rows]
        use = buf.pv[rows] & (times[:, None] >= self.segment_start[None, :])
        step_share, joined_share, leaf_share = self.extrapolation_share if share is None else share
        reseat = self.reseat_refuted if reseat is None else reseat
        if share is None:
            weight = np.where(use, buf.w[rows], 0.0)
            w_joined = np.where(use, buf.wc[rows], 0.0) if joined_share != step_share else weight
            if leaf_share != step_share:  # (a share other than the step test's for a leaf: its own weights)
                var = 1.0 / np.where(weight > 0, weight, 1.0)
                extra = np.nan_to_num(self.base.sigma, nan=0.0) ** 2 * self.base.leverage(buf.Q[rows])
                weight = np.where(weight > 0, 1.0 / np.maximum(var + (leaf_share - step_share) * extra, 1e-300), 0.0)
        else:
            extra = np.nan_to_num(self.base.sigma, nan=0.0) ** 2 * self.base.leverage(buf.Q[rows])
            nv = np.where(use, buf.nv[rows], 0.0)
            live = use & (nv > 0)
            nv = np.where(live, nv, 1.0)
            weight = np.where(live, 1.0 / (nv + leaf_share * extra), 0.0)
            w_joined = np.where(live, 1.0 / (nv + joined_share * extra), 0.0) if joined_share != leaf_share else weight
        head = int(np.searchsorted(rows, full.start + cut))
        weight[:head] *= stride
        if w_joined is not weight:
            w_joined[:head] *= stride
        onset_row = int(np.searchsorted(rows, full.start + onset_row))
        post = slice(rows[onset_row], full.stop)
        g, Q = buf.g[rows], buf.Q[rows]
        near = touching(self.joints, self.joints[fired]) & ready
        u_post = residual(buf.g[post][:, near], buf.Q[post][:, near], c[near], l[near])
        weight[onset_row:, near] = _with_own_noise(u_post, weight[onset_row:, near])
        if w_joined is not weight:
            w_joined[onset_row:, near] = _with_own_noise(u_post, w_joined[onset_row:, near])

        def swapped(perm, touched):
            return joint_geometry(buf.R[post][:, perm], buf.t[post][:, perm], self.joints[touched])

        k = max(2, self.noise_frames // 4)  # a few frames each side of the onset, against the noise
        before = slice(max(full.start, post.start - k), post.start)
        after = slice(post.start, min(post.stop, post.start + k))
        pos = {}
        for name, span in (("before", before), ("after", after)):
            v = buf.valid[span]
            pos[name] = np.einsum("lm,lma->ma", v, buf.t[span]) / np.maximum(v.sum(axis=0), 1)[:, None]
            pos[name + "_ok"] = v.any(axis=0)

        def swap_plausible(a, b):
            # Two sensors that swapped streams jump into each other's place; a slip or soft tissue
            # moves a sensor by centimetres along a continuous path.
            if not (pos["before_ok"][[a, b]].all() and pos["after_ok"][[a, b]].all()):
                return False
            p0, p1 = pos["before"], pos["after"]
            stay = np.linalg.norm(p1[a] - p0[a]) + np.linalg.norm(p1[b] - p0[b])
            cross = np.linalg.norm(p1[a] - p0[b]) + np.linalg.norm(p1[b] - p0[a])
            return bool(cross < stay)

        win = Window(times, g, Q, use, weight, onset_row, c, l, swapped, swap_plausible,
                     None if w_joined is weight else w_joined)
        att = attribute(win, self.joints, self._nbrs, ready, fired, self.m, self.min_jump, self.min_evidence,
                        late_rows=self._pending.merge, min_tail=self.min_frames, more_looks=more_looks,
                        reseat_refuted=reseat)
        if att.kind in ("slip", None) and att.later_row is not None:
            return att, buf.index_of(int(rows[att.later_row]))
        if att.kind == "slip":
            J = self.joints
            child, parent = J[:, 0] == att.sensor, J[:, 1] == att.sensor
            # The sensor's own skin moves with the angles of its own joints: that is the pose to match.
            pose = child | parent
            if verify:
                # Each of its joints' residuals also carries the skin of the sensor at the joint's other end,
                # which moves with that sensor's joints: all of them must be back in the same pose.
                ends = present(J[pose])
                pose = touching(J, ends)
            back = came_back(self._history, float(buf.times[post.start]), self.segment_start, buf.times[post],
                             buf.g[post], buf.Q[post], buf.pv[post], weight[onset_row:], child, parent, pose, c, l,
                             att.step)
            if back is not None and back > CAME_BACK_NATS:  # (None: poses not seen before, no verdict; the slip stands)
                self.came_back += 1
                return Attribution(None, evidence=att.evidence), None
            if verify and (back is None or back > -CAME_BACK_NATS):
                # The second look counts none of the extrapolation: skin in a new pose can pass it too. Its slip
                # stands only where the same pose before the onset shows the step stayed, by the same odds.
                return Attribution(None, evidence=att.evidence), None
            att = self._leaf_or_body(att, float(buf.times[post.start]), buf.times[post], buf.g[post], buf.Q[post],
                                     buf.pv[post], weight[onset_row:], c, l)
        return att, None

    def _leaf_or_body(self, att: Attribution, before: float, times, g, Q, pv, weight, c, l) -> Attribution:
        """A leaf's slip (a hand) and its neighbour's (the forearm) step the joint they share alike; only the
        neighbour's other joints (the elbow) tell them apart, and soft tissue in a new pose can mimic the
        neighbour's step there. A slip named on the neighbour is the leaf's where those joints sit, since
        the onset, where they sat in the same pose before it."""
        J = self.joints
        s = att.sensor
        count = np.bincount(J.ravel(), minlength=self.m)
        if count[s] < 2:
            # The other way round (a leaf's slip that is its neighbour's) is not decided here: a step at the
            # elbow is also what skin moving with a joint the pose match leaves out (the shoulder) makes (the
            # sweep renamed ten hands and feet wrongly that way, against two forearms rightly).
            return att
        mine = (J == s).any(axis=1)
        half = 0.5 * att.steps[s]
        for j in np.flatnonzero(mine):
            leaf = self._across(j, s)
            if count[leaf] != 1 or np.linalg.norm(att.steps[leaf]) < self.min_jump:
                continue
            rest = mine.copy()
            rest[j] = False
            # The same pose: first every joint of the sensor (its skin moves with them all), then, where a
            # fast limb has not been there before, the joints that tell the two apart alone. Back means
            # nearer where they sat than half the step either way: a shift half a step along it or against
            # it is neither (the knee after a shin's slip, sweep seeds 5 and 6).
            for pose in (mine, rest):
                backs = came_back(self._history, before, self.segment_start, times, g, Q, pv, weight,
                                  rest & (J[:, 0] == s), rest & (J[:, 1] == s), pose, c, l, np.stack([half, -half]))
                if backs is not None:
                    break
            if backs is None or backs.min() <= CAME_BACK_NATS:
                continue
            back = float(backs.min())
            share = float(1.0 / (1.0 + np.exp(-back)))
            cands = [(leaf, share)] + ([(s, 1.0 - share)] if 1.0 - share >= CANDIDATE_SHARE else [])
            step = att.steps[leaf]
            self.renamed += 1
            return replace(att, sensor=leaf, candidates=cands, confidence=share, joints=[int(j)],
                           jump_m=float(np.linalg.norm(step)), step=step)
        return att

    def _refresh(self, now: float, c, l) -> None:
        """Recompute every joint's baseline with the current estimates from the lagged window."""
        buf = self._buf
        sl = buf.between(now - self.lag_s - self.baseline_s, now - self.lag_s)
        stride = max(1, (sl.stop - sl.start) // self._fit_rows)
        Q = buf.Q[sl]
        mask = buf.pv[sl] & (buf.times[sl][:, None] >= self.segment_start[None, :])
        u, Qs, ms = residual(buf.g[sl][::stride], Q[::stride], c, l), Q[::stride], mask[::stride]
        self.base = smooth_baseline(u, Qs, ms, self._nbrs, self.scale_floor)
        self.base.frames = mask.sum(axis=0)
        with np.errstate(invalid="ignore"):
            self.rms = np.sqrt(np.where(ms, (u * u).sum(axis=-1), 0.0).sum(axis=0) / ms.sum(axis=0))
        enough = self.base.frames >= 0.6 * min(self.warmup_s, self.baseline_s) * self.rate_hz
        settled = now - self.segment_start >= max(self.warmup_s, self.lag_s)
        # A joint's residual is tracker noise and soft tissue, a couple of centimetres at most; a pair
        # whose residual is larger than max_rms_m is two bodies that are not joined (an object in the
        # hand, a wrong tree edge): steps in it are no slips, and it is not watched.
        joined = self.rms <= self.max_rms
        self.ready = enough & settled & np.isfinite(self.base.sigma) & joined
        self._c_ref, self._l_ref = np.array(c, dtype=float), np.array(l, dtype=float)
        self._last_refresh = now
        self._fresh = None  # every deviation must be worked out again against the new baseline


def _checked_joints(joints, m: int) -> np.ndarray:
    J = np.asarray(joints, dtype=int).reshape(-1, 2)
    if J.size and (J.min() < 0 or J.max() >= m or (J[:, 0] == J[:, 1]).any()):
        raise SlippageError(f"joints must be (child, parent) pairs of distinct sensor indices below {m}")
    return J


def _with_own_noise(x: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Weights 1/σ² no larger than the window's own noise allows: σ² per joint from the differences
    inside the window, where that exceeds the trailing estimate (a limb speeding up)."""
    live = weight > 0
    both = live[1:] & live[:-1]
    d2 = np.where(both, ((x[1:] - x[:-1]) ** 2).sum(axis=-1), 0.0)
    n = both.sum(axis=0)
    own = np.where(n >= 2, d2.sum(axis=0) / (6.0 * np.maximum(n, 1)), 0.0)
    with np.errstate(divide="ignore"):
        return np.where(live, 1.0 / np.maximum(1.0 / np.where(live, weight, 1.0), own[None, :]), 0.0)


def detect_slips(take, calibration=None, *, joints=None, c=None, l=None, batch_s: float = 10.0,
                 frame_step: float | None = None, **options) -> list:
    """Slip and swap events in a recorded take, replayed through a `SlipMonitor` (which examines the
    frames `step_s` at a time, as live, whatever the `batch_s` pieces they are handed over in).

    The frame-rate step test is off here unless `frame_step` is given (the live monitor's 20 nats finds
    its events): it would triple the scan's CPU, and `flockcal fit` has 1 s for a 30 s take, scan
    included (docs/slippage.md, sixth round).

    take: a `flockcal.takes.Take`, any `ChunkedTake` (a take file read a piece at a time), or anything with
    rotations, positions, rate_hz and optionally valid, times, names. Joint estimates come from `calibration` (a `Calibration` or its docs/design.md §5 dict)
    or from `joints` (p, 2) with `c`, `l` (p, 3). A whole-take fit is blended across a slip; the
    monitor's baselines are taken in both sensor frames of each joint, so the step still shows.
    """
    given = getattr(take, "names", None)
    m = len(given) if given is not None else np.shape(take.rotations)[1]
    rate = float(take.rate_hz)
    names = tuple(given or (str(i) for i in range(m)))
    if calibration is not None:
        joints, c, l = joints_from_calibration(calibration, names)
    if joints is None or c is None or l is None:
        raise SlippageError("detect_slips needs a calibration or joints with c and l (fit the take first)")
    mon = SlipMonitor(joints, m, rate, names, frame_step=frame_step, **options)
    # A piece at a time (a take on disk is read so: memory stays a piece and the monitor's window).
    for f in frames_of(take, max(1, int(round(batch_s * rate)))):
        mon.add_frames(f.times, f.rotations, f.positions, f.valid, c, l)
    return mon.events


def joints_from_calibration(calibration, names) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(joints (p, 2) as indices into `names`, c (p, 3), l (p, 3)) from a Calibration, a fit with
    `.calibration()`, or a docs/design.md §5 dict (read by `calibration_from_json`)."""
    from flockcal.solver.calibration_json import as_calibration

    cal = as_calibration(calibration, names=names, error=SlippageError)
    index = {n: i for i, n in enumerate(names)}
    pairs, c, l = cal.joint_arrays()
    try:
        J = np.array([[index[cal.names[a]], index[cal.names[b]]] for a, b in pairs.tolist()], dtype=int).reshape(-1, 2)
    except KeyError as exc:
        raise SlippageError(f"the calibration names sensor {exc.args[0]!r}, which this take does not have") from None
    return J, c, l
