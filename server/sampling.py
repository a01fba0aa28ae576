"""What the live service watches in the session's frames: each joint's residual rms, sampled
`residual_hz` times a second against the newest fit, and the slip loop (solver/slippage/watch.py).
Both run on the pipeline thread only and own their state.
"""

from __future__ import annotations

import logging
from collections import deque

import numpy as np

from flockcal.server.fitting import FitJoints, fit_joints, json_safe
from flockcal.server.live_session import LiveSession
from flockcal.server.snapshot import ResidualSample
from flockcal.solver.calibration import Calibration

log = logging.getLogger(__name__)

RECENT_RESIDUALS = 400


class ResidualSampler:
    """Residual rms per joint of the live fit, one sample per `period` s of session time.

    Pipeline thread only. Frames wait in `_pending` until a sample's worth has arrived: the cost of these
    small array steps is per call, and the reader hands frames over ~100 times a second."""

    def __init__(self, names, period: float):
        self.names = tuple(names)
        self.period = float(period)
        self.recent: deque[ResidualSample] = deque(maxlen=RECENT_RESIDUALS)
        self._seq = 0
        self._joint_cache: tuple[Calibration, FitJoints] | None = None
        self.reset()

    def reset(self) -> None:
        self._pending: list = []  # session frames (times, R, t, valid) not yet in a residual sample
        self._joints: tuple = ()
        self._sumsq = self._count = None
        self._last_emit: float | None = None
        self._time = 0.0

    def joints(self, calibration: Calibration) -> FitJoints:
        """The fit's joints as arrays, worked out once per fit."""
        if self._joint_cache is None or self._joint_cache[0] is not calibration:
            self._joint_cache = (calibration, fit_joints(calibration, self.names))
        return self._joint_cache[1]

    def add(self, live: LiveSession, ts, R, t, valid) -> None:
        self._pending.append((ts, R, t, valid))
        if self._pending[-1][0][-1] - self._pending[0][0][0] >= self.period:
            self.drain(live)

    def drain(self, live: LiveSession) -> None:
        pending, self._pending = self._pending, []
        if pending:
            self._step(live, *(np.concatenate([p[k] for p in pending]) for k in range(4)))

    def _step(self, live: LiveSession, ts, R, t, valid) -> None:
        cal = live.calibration
        if cal is None or not len(cal.joints):
            return
        fj = self.joints(cal)
        if fj.joints != self._joints:
            self.flush(live)
            self._joints = fj.joints
            self._sumsq = np.zeros(len(fj.joints))
            self._count = np.zeros(len(fj.joints))
        ci, pj = fj.pairs[:, 0], fj.pairs[:, 1]
        e = (np.einsum("npab,pb->npa", R[:, ci], fj.c) + t[:, ci]
             - np.einsum("npab,pb->npa", R[:, pj], fj.l) - t[:, pj])
        sq = np.einsum("npa,npa->np", e, e)
        ok = valid[:, ci] & valid[:, pj] & np.isfinite(sq)
        sq = np.where(ok, sq, 0.0)
        self._sumsq += sq.sum(axis=0)
        self._count += ok.sum(axis=0)
        self._time = float(ts[-1])
        if self._last_emit is None:
            self._last_emit = float(ts[0])
        if self._time - self._last_emit >= self.period:
            self.flush(live)

    def flush(self, live: LiveSession | None) -> None:
        """Emit the sample being gathered (at its period, on a new tree, and at the session's end)."""
        if self._count is None or not self._count.any() or live is None:
            return
        rms = np.sqrt(self._sumsq / np.maximum(self._count, 1)) * 1000.0
        values = {j[0]: round(float(v), 4) for j, v, c in zip(self._joints, rms, self._count) if c > 0}
        self._seq += 1
        sample = ResidualSample(self._seq, self._time, values)
        self.recent.append(sample)
        live.residual_rows.append((sample.time_s, values))
        self._sumsq[:] = 0
        self._count[:] = 0
        self._last_emit = self._time


def watch_step(live: LiveSession, ts, R, t, valid, catch_up: int = 1) -> list[dict]:
    """Frames through the session's slip loop; the events it gives, as dicts for the store.

    Pipeline thread only. The loop refits the watched joints between its micro-batches and opens the
    slipped sensors' segments itself. A loop that fails stops watching, once: the failure is logged with
    its traceback and becomes a tracker event; recording and fitting go on."""
    watch = live.watch
    had_failed = watch.failure is not None
    found = watch.feed(ts, R, t, valid, catch_up)
    return _events(live, found, had_failed)


def watch_flush(live: LiveSession) -> list[dict]:
    """The slip loop's held remainder, at the session's end."""
    had_failed = live.watch.failure is not None
    return _events(live, live.watch.flush(), had_failed)


def _events(live: LiveSession, found: list, had_failed: bool) -> list[dict]:
    events = []
    for ev in found:
        d = ev.to_dict()
        d["type"] = d.pop("kind", "slip")
        events.append(json_safe(d))
    exc = live.watch.failure
    if exc is not None and not had_failed:
        log.error("slip monitor failed; slips are no longer watched in session %s", live.id,
                  exc_info=(type(exc), exc, exc.__traceback__))
        events.append({
            "type": "tracker", "kind": "slip_watch_failed",
            "message": f"slip detection stopped for this session ({type(exc).__name__}: {exc}); "
                       f"recording and fitting go on; restart the session to watch for slips again"})
    return events
