"""Sensor slippage and swap detection (design.md §4): a live `SlipMonitor` fed the same micro-batches as
the accumulator plus the current joint estimates, and `detect_slips` for a recorded take.

Per joint, a window-limited GLR test for a step in the residual vector (seen from either sensor of
the joint, against that joint's own robust baseline, weighted by the noise the data shows) raises a
suspicion; `slippage_attribution` then names the sensor whose joints
all stepped (or the pair that swapped) before an event is reported.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flockcal.errors import FlockcalError
from flockcal.solver.slippage_attribution import attribute
from flockcal.solver.slippage_stats import (Baseline, affine_baseline, joint_frames, local_variance,
                                            step_design_sums, window_glr)


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
        """The `slip_events` entry of design.md §5 (extended with kind, confidence and detected_s)."""
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


class _FrameBuffer:
    """The most recent frames (times, rotations, positions, valid) with their global frame index."""

    def __init__(self, capacity: int, m: int):
        self.capacity = capacity
        size = 2 * capacity
        self.times = np.zeros(size)
        self.R = np.zeros((size, m, 3, 3))
        self.t = np.zeros((size, m, 3))
        self.valid = np.zeros((size, m), dtype=bool)
        self.lo = self.hi = 0
        self.first_index = 0  # global index of slot lo

    def append(self, times, R, t, valid) -> int:
        """Store a batch (at most `capacity` frames); returns the global index of its first frame."""
        n = len(times)
        if self.hi + n > len(self.times):
            keep = min(self.hi - self.lo, self.capacity - n)
            src = slice(self.hi - keep, self.hi)
            for a in (self.times, self.R, self.t, self.valid):
                a[:keep] = a[src]
            self.first_index += self.hi - keep - self.lo
            self.lo, self.hi = 0, keep
        sl = slice(self.hi, self.hi + n)
        self.times[sl], self.R[sl], self.t[sl], self.valid[sl] = times, R, t, valid
        self.hi += n
        if self.hi - self.lo > self.capacity:
            drop = self.hi - self.lo - self.capacity
            self.lo += drop
            self.first_index += drop
        return self.first_index + (self.hi - self.lo) - n

    def since(self, index: int) -> slice:
        """Slots holding global frames index… (clipped to what is still stored)."""
        return slice(self.lo + max(index - self.first_index, 0), self.hi)

    def between(self, t0: float, t1: float) -> slice:
        times = self.times[self.lo:self.hi]
        a, b = np.searchsorted(times, [t0, t1], side="left")
        return slice(self.lo + a, self.lo + b)

    def global_index(self, sl: slice) -> np.ndarray:
        return self.first_index + np.arange(sl.start - self.lo, sl.stop - self.lo)


class SlipMonitor:
    """Live slippage detector over the p joints of a tree (or any joint list).

    joints: (p, 2) sensor indices (child, parent). Feed `update` every batch of frames with the current
    joint estimates c, l (p, 3) (the child and parent frame coordinates of each joint centre); it returns
    the events confirmed in this batch. After an event the affected joints re-baseline from the slip
    time on (they stay quiet for `warmup_s`, at least `lag_s`); the others keep their state.

    The test is in units of each joint's own noise, measured from the data: `threshold` and
    `min_evidence` are nats (log-likelihood ratios), `min_jump_m` is the smallest step worth reporting
    and `scale_floor_m` stops exact, noise-free data from dividing by zero.
    """

    def __init__(self, joints, n_sensors: int, rate_hz: float, names=None, *,
                 min_jump_m: float = 0.01, warmup_s: float = 5.0, baseline_s: float = 8.0,
                 lag_s: float = 1.0, refresh_s: float = 0.5, window_s: float = 0.5, noise_s: float = 0.25,
                 threshold: float = 25.0, attribute_s: float = 0.15, min_frames: int = 4,
                 min_evidence: float = 20.0, scale_floor_m: float = 2e-4):
        J = np.asarray(joints, dtype=int).reshape(-1, 2)
        if J.size and (J.min() < 0 or J.max() >= n_sensors or (J[:, 0] == J[:, 1]).any()):
            raise SlippageError(f"joints must be (child, parent) pairs of distinct sensor indices below {n_sensors}")
        if not rate_hz > 0:
            raise SlippageError(f"rate_hz must be positive, got {rate_hz!r}")
        if not lag_s > window_s:
            raise SlippageError("lag_s must exceed window_s, so a step is never inside its own baseline")
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
        self.threshold, self.attribute_s, self.min_frames = threshold, attribute_s, int(min_frames)
        self.min_evidence, self.scale_floor = min_evidence, scale_floor_m
        p = len(J)
        cap = int(np.ceil((baseline_s + lag_s + 1.0) * rate_hz))
        self._buf = _FrameBuffer(cap, self.m)
        self._chunk = max(1, int(round(refresh_s * rate_hz)))
        self.segment_start = np.full(p, np.nan)  # time each joint's current segment began
        self.ready = np.zeros(p, dtype=bool)
        self.base: Baseline | None = None
        self._c_ref = np.full((p, 3), np.nan)
        self._l_ref = np.full((p, 3), np.nan)
        self._last_refresh = -np.inf
        self._quiet = np.full(p, -1, dtype=np.int64)  # global frame index: no step may start before it
        self._pending: tuple[int, np.ndarray] | None = None  # (onset frame, joints that fired)
        self.score = np.zeros(p)  # latest GLR score per joint (nats), for display
        self.events: list[SlipEvent | SwapEvent] = []

    # -- public -------------------------------------------------------------------------------------
    def update(self, times, rotations, positions, valid=None, c=None, l=None) -> list:
        """Take a batch of frames and the current joint estimates; return the events confirmed now."""
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
        p = len(self.joints)
        if c is None or l is None:
            raise SlippageError("update needs the current joint estimates c and l, each (p, 3)")
        c = np.asarray(c, dtype=float).reshape(p, 3)
        l = np.asarray(l, dtype=float).reshape(p, 3)
        v = v & np.isfinite(R).all(axis=(2, 3)) & np.isfinite(t).all(axis=2)
        R = np.where(v[..., None, None], R, 0.0)
        t = np.where(v[..., None], t, 0.0)
        if np.isnan(self.segment_start).all() and n:
            self.segment_start[:] = ts[0]
        out = []
        for a in range(0, n, self._chunk):
            b = min(n, a + self._chunk)
            out += self._process(ts[a:b], R[a:b], t[a:b], v[a:b], c, l)
        self.events += out
        return out

    def status(self) -> dict:
        """Per joint (by child name): watching yet, latest step evidence (nats) and the current
        segment's start, plus every event so far, for a status page."""
        joints = {
            self.names[int(c)]: {"ready": bool(r), "score": round(float(sc), 2), "segment_start_s": None if st != st else float(st)}
            for (c, _), r, sc, st in zip(self.joints, self.ready, self.score, self.segment_start)
        }
        return {"joints": joints, "threshold": self.threshold, "events": [e.to_dict() for e in self.events]}

    # -- internals ----------------------------------------------------------------------------------
    def _process(self, ts, R, t, v, c, l) -> list:
        buf = self._buf
        g0 = buf.append(ts, R, t, v)
        n = len(ts)
        now = float(ts[-1])
        finite = np.isfinite(c).all(axis=1) & np.isfinite(l).all(axis=1)
        cc, ll = np.where(finite[:, None], c, 0.0), np.where(finite[:, None], l, 0.0)
        if now - self._last_refresh >= self.refresh_s or self.base is None:
            self._refresh(now, cc, ll)
        else:
            # New estimates change every residual by δc − Q δl, which the baseline's form a − Q b
            # follows exactly: shift it instead of recomputing.
            self.base.a = self.base.a + (cc - self._c_ref)
            self.base.b = self.base.b + (ll - self._l_ref)
            self._c_ref, self._l_ref = cc.copy(), ll.copy()
        ready = self.ready & finite
        if self._pending is None and not ready.any():
            return []
        # Residuals of the recent frames with the current estimates: the step test's window plus the
        # frames the local noise level needs, all recomputed so that c, l moving never looks like a step.
        sl = buf.since(g0 + n - (self.window + self.noise_frames + n))
        gidx = buf.global_index(sl)
        x, y, pv, weight = self._deviations(buf.R[sl], buf.t[sl], buf.valid[sl], cc, ll)
        earliest = np.maximum(self._quiet, 0) - gidx[0]
        xs = np.concatenate([x, y], axis=1)  # child-frame and parent-frame series side by side
        ws = np.concatenate([weight, weight], axis=1)
        score, start = window_glr(xs, ws, n, self.window, 0.5 * self.min_jump, self.min_frames,
                                  np.concatenate([earliest, earliest]))
        p = len(self.joints)
        which = score[:, p:] > score[:, :p]
        score = np.where(which, score[:, p:], score[:, :p])
        start = np.where(which, start[:, p:], start[:, :p])
        score = np.where(ready[None, :], score, 0.0)
        self.score = score[-1]
        if self._pending is None:
            hit = score >= self.threshold
            if not hit.any():
                return []
            k = int(np.flatnonzero(hit.any(axis=1))[0])
            fired = hit[k]
            onset = int(gidx[0] + start[k][fired].min())
            self._pending = (onset, fired)
        onset, fired = self._pending
        wsl = buf.since(onset)
        if now - float(buf.times[wsl.start]) < self.attribute_s:
            return []  # gather a little more evidence before naming the sensor
        self._pending = None
        # The window since the onset, with the noise level measured on the frames before it as well;
        # residuals with the estimates the baseline sums were made with, so the two halves agree.
        full = buf.since(onset - self.noise_frames)
        x2, _, _, w2 = self._deviations(buf.R[full], buf.t[full], buf.valid[full], cc, ll)
        cut = wsl.start - full.start
        Rw, tw, vw = buf.R[wsl], buf.t[wsl], buf.valid[wsl]
        cp, lp = self._c_pre, self._l_pre
        u2, Q2 = joint_frames(Rw, tw, self.joints, cp, lp)
        pv2 = vw[:, self.joints[:, 0]] & vw[:, self.joints[:, 1]]

        def swapped(perm, touched):
            return joint_frames(Rw[:, perm], tw[:, perm], self.joints[touched], cp[touched], lp[touched])

        w2 = _with_own_noise(x2[cut:], w2[cut:])
        att = attribute(self._pre, u2, Q2, pv2, w2, self.joints, ready, fired, self.m,
                        self.min_jump, self.min_evidence, swapped)
        if att.kind is None:
            self._quiet[fired] = g0 + n  # look for a new step from here on, not the same evidence again
            return []
        affected = np.asarray(att.joints, dtype=int)
        t_onset = float(buf.times[wsl.start])
        names = tuple(self.names[int(self.joints[j, 0])] for j in affected)
        if att.kind == "slip":
            ev = SlipEvent(t_onset, self.names[att.sensor], tuple(self.names[k] for k, _ in att.candidates),
                           att.confidence, names, 1000.0 * att.jump_m, now, att.sensor, tuple(affected.tolist()))
        else:
            ev = SwapEvent(t_onset, self.names[att.sensor], self.names[att.other], names, 1000.0 * att.jump_m,
                           att.confidence, now, (att.sensor, att.other), tuple(affected.tolist()))
        self.segment_start[affected] = t_onset
        self.ready[affected] = False
        self._quiet[fired] = g0 + n
        self._quiet[affected] = onset
        return [ev]

    def _deviations(self, R, t, v, c, l):
        """Deviation of each frame's residual from the baseline in the child and the parent frame,
        pair validity, and the weight 1/σ² per frame from the local noise level (n, p)."""
        u, Q = joint_frames(R, t, self.joints, c, l)
        x, y = self.base.deviations(u, Q)
        pv = v[:, self.joints[:, 0]] & v[:, self.joints[:, 1]]
        var = local_variance(x, pv, self.noise_frames)
        floor = np.maximum(0.5 * np.nan_to_num(self.base.sigma, nan=0.0), self.scale_floor) ** 2
        ok = np.isfinite(var)
        weight = np.where(pv & ok, 1.0 / np.maximum(np.where(ok, var, 1.0), floor), 0.0)
        return x, y, pv, weight

    def _refresh(self, now: float, c, l) -> None:
        """Recompute every joint's baseline with the current estimates from the lagged window."""
        buf = self._buf
        sl = buf.between(now - self.lag_s - self.baseline_s, now - self.lag_s)
        R, t, v = buf.R[sl], buf.t[sl], buf.valid[sl]
        times = buf.times[sl]
        u, Q = joint_frames(R, t, self.joints, c, l)
        mask = v[:, self.joints[:, 0]] & v[:, self.joints[:, 1]]
        mask &= times[:, None] >= self.segment_start[None, :]
        self.base = affine_baseline(u, Q, mask, self.scale_floor)
        wpre = np.where(mask, 1.0 / np.nan_to_num(self.base.sigma, nan=np.inf)[None, :] ** 2, 0.0)
        self._pre = step_design_sums(u, Q, wpre, None)
        self._c_pre, self._l_pre = np.array(c, dtype=float), np.array(l, dtype=float)
        enough = self.base.frames >= 0.6 * min(self.warmup_s, self.baseline_s) * self.rate_hz
        settled = now - self.segment_start >= max(self.warmup_s, self.lag_s)
        self.ready = enough & settled & np.isfinite(self.base.sigma)
        self._c_ref, self._l_ref = np.array(c, dtype=float), np.array(l, dtype=float)
        self._last_refresh = now


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


def attributes_slip_to(event, sensor: str, names, parent) -> bool:
    """True if `event` (a SlipEvent, or a SwapEvent read as one) blames `sensor`, or offers exactly `sensor`
    and the body it hangs on or off when that body is a leaf (a leaf's single joint cannot tell the two
    apart). `parent`: index array over `names`, −1 at the root. How tests and benchmarks score attribution."""
    if event.sensor == sensor:
        return True
    pair = set(event.candidates)
    if sensor not in pair or len(pair) != 2:
        return False
    names, parent = list(names), np.asarray(parent)
    a, b = (names.index(x) for x in pair)
    leaf = a if parent[a] == b else b if parent[b] == a else None
    return leaf is not None and not np.any(parent == leaf)


def detect_slips(take, calibration=None, *, joints=None, c=None, l=None, batch_s: float = 0.25,
                 **options) -> list:
    """Slip and swap events in a recorded take, replayed through a `SlipMonitor` in live-sized batches.

    take: a `flockcal.takes.Take` (or anything with rotations, positions, rate_hz and optionally valid,
    times, names). Joint estimates come from `calibration` (a `Calibration` or its design.md §5 dict)
    or from `joints` (p, 2) with `c`, `l` (p, 3). A whole-take fit is blended across a slip; the
    monitor's baselines are taken in both sensor frames of each joint, so the step still shows.
    """
    R = np.asarray(take.rotations, dtype=float)
    t = np.asarray(take.positions, dtype=float)
    n, m = R.shape[:2]
    rate = float(take.rate_hz)
    names = tuple(getattr(take, "names", None) or (str(i) for i in range(m)))
    valid = getattr(take, "valid", None)
    times = getattr(take, "times", None)
    times = np.arange(n) / rate if times is None else np.asarray(times, dtype=float)
    if calibration is not None:
        joints, c, l = joints_from_calibration(calibration, names)
    if joints is None or c is None or l is None:
        raise SlippageError("detect_slips needs a calibration or joints with c and l (fit the take first)")
    mon = SlipMonitor(joints, m, rate, names, **options)
    step = max(1, int(round(batch_s * rate)))
    for a in range(0, n, step):
        b = min(n, a + step)
        mon.update(times[a:b], R[a:b], t[a:b], None if valid is None else valid[a:b], c, l)
    return mon.events


def joints_from_calibration(calibration, names) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(joints (p, 2), c (p, 3), l (p, 3)) from a Calibration or its design.md §5 dict."""
    d = calibration.to_dict() if hasattr(calibration, "to_dict") else calibration
    try:
        entries = d["joints"]
    except (KeyError, TypeError):
        raise SlippageError("the calibration has no 'joints' list (expected the `flockcal fit --json` shape)") from None
    index = {n: i for i, n in enumerate(names)}
    try:
        J = np.array([[index[e["child"]], index[e["parent"]]] for e in entries], dtype=int).reshape(-1, 2)
    except KeyError as exc:
        raise SlippageError(f"the calibration names sensor {exc.args[0]!r}, which this take does not have") from None
    c = np.array([e["c"] for e in entries], dtype=float).reshape(-1, 3)
    l = np.array([e["l"] for e in entries], dtype=float).reshape(-1, 3)
    return J, c, l
