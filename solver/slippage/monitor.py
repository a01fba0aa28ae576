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
from dataclasses import replace

import numpy as np

from flockcal.frames import frames_of
from flockcal.solver.slippage.attribution import Attribution
from flockcal.solver.slippage.buffer import FrameBuffer
from flockcal.solver.slippage.baseline import neighbours
from flockcal.solver.slippage.confirming import ConfirmingTest
from flockcal.solver.slippage.events import SlipEvent, SlippageError, SwapEvent
from flockcal.solver.slippage.framescan import FrameScan
from flockcal.solver.slippage.pending import PendingSuspicions
from flockcal.solver.slippage.revisit import PoseHistory
from flockcal.solver.slippage.settings import SlipSettings
from flockcal.solver.slippage.stats import touching
from flockcal.solver.slippage.steptest import StepTest

__all__ = ["SlipEvent", "SlipMonitor", "SlipSettings", "SlippageError", "SwapEvent", "detect_slips",
           "joints_from_calibration"]


class SlipMonitor(StepTest, ConfirmingTest, FrameScan):
    """Live slippage detector over the p joints of a tree (or any joint list).

    joints: (p, 2) sensor indices (child, parent). Feed `add_frames` every batch of frames with the current
    joint estimates c, l (p, 3) (the child and parent frame coordinates of each joint centre); it returns
    the events confirmed in this batch. After an event the affected joints re-baseline from the slip
    time on (they stay quiet for `warmup_s`, at least `lag_s`); the others keep their state.

    How it watches is a `SlipSettings` (`settings`, the service's defaults when None); keyword `options`
    name its fields and override them (`SlipMonitor(J, m, rate, names, warmup_s=2.0)`). The monitor runs
    three parts on one frame buffer: the step test (`steptest`) raises suspicions, the confirming test
    (`confirming`) names the sensor or drops them, and the frame-rate step test (`framescan`) reports a
    step it finds at once.
    """

    def __init__(self, joints, n_sensors: int, rate_hz: float, names=None, settings: SlipSettings | None = None,
                 **options):
        J = _checked_joints(joints, n_sensors)
        if not rate_hz > 0:
            raise SlippageError(f"rate_hz must be positive, got {rate_hz!r}")
        settings = SlipSettings() if settings is None else settings
        self.settings = replace(settings, **options) if options else settings
        self.joints = J
        self.m = int(n_sensors)
        self.rate_hz = float(rate_hz)
        self.names = tuple(str(x) for x in names) if names is not None else tuple(str(i) for i in range(self.m))
        if len(self.names) != self.m:
            raise SlippageError(f"{len(self.names)} names given for {self.m} sensors")
        s = self.settings
        self._nbrs = neighbours(J)
        p = len(J)
        cap = int(np.ceil((s.baseline_s + s.lag_s + 1.0) * rate_hz))
        self._buf = FrameBuffer(cap, self.m, J)
        # Poses of the last revisit_s at about 50 Hz, to see whether the residual came back with the pose.
        self._history = PoseHistory(J, self.m, rate_hz, s.revisit_s, every=int(round(rate_hz / 50.0)))
        self._chunk = max(1, int(round(s.step_s * rate_hz)))
        self.segment_start = np.full(p, np.nan)  # time each joint's current segment began
        self._t0 = np.nan  # time of the first frame seen
        self._fed = False
        self._quiet = np.full(p, -1, dtype=np.int64)  # global frame index: no step may start before it
        self._pending = PendingSuspicions(p, int(round(s.merge_s * rate_hz)))
        self.events: list[SlipEvent | SwapEvent] = []
        self._init_step_test(p)
        self._init_confirming_test()
        self._init_frame_scan()

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
                                 "joined": not rms > self.settings.max_rms_m}
            for (c, _), r, sc, st, rms in zip(self.joints, self.ready, self.score, self.segment_start, self.rms)
        }
        return {"joints": joints, "threshold": self.settings.threshold, "events": [e.to_dict() for e in self.events]}

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
        due = ts[ends[0] - 1] - self._last_refresh >= self.settings.refresh_s or self.base is None
        last = ts[ends[0] - 1] if due else self._last_refresh
        limit = a + int(round(self.settings.refresh_s * self.rate_hz)) + self._chunk
        while ends[-1] < min(n, limit):
            nxt = min(n, ends[-1] + self._chunk)
            if ts[nxt - 1] - last >= self.settings.refresh_s:
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
        if now - self._last_refresh >= self.settings.refresh_s or self.base is None:
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
            hit = score >= self.settings.threshold  # (steps j…, p)
            for k in range(j, len(ends)):
                self.score = score[k - j]
                self._pending.add(hit[k - j], first_row + start[k - j])
                if self.settings.frame_step_nats is not None:
                    self._hits.extend((int(first_row + start[k - j, q]), q) for q in np.flatnonzero(hit[k - j]))
                now = float(ts[ends[k] - 1])
                changed, ev = self._suspicions(now, step_last[k], ready, c, l) if self._pending else (False, [])
                if self.settings.frame_step_nats is not None:
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

    def _across(self, j: int, s: int) -> int:
        """The sensor at the other end of joint j from sensor s."""
        return int(self.joints[j, 1] if self.joints[j, 0] == s else self.joints[j, 0])


def _checked_joints(joints, m: int) -> np.ndarray:
    J = np.asarray(joints, dtype=int).reshape(-1, 2)
    if J.size and (J.min() < 0 or J.max() >= m or (J[:, 0] == J[:, 1]).any()):
        raise SlippageError(f"joints must be (child, parent) pairs of distinct sensor indices below {m}")
    return J

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
