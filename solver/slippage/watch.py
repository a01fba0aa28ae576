"""The one slip loop, live and replayed: frames → segmented accumulator → tree-joint refits on their
segments → `SlipMonitor` → new segments. The server's live pipeline and every replay of a take (tests,
benchmarks) run this object, at the cadence the slip figures of docs/slippage.md were measured at.
"""

from __future__ import annotations

import logging

import numpy as np

from flockcal.solver.fits import JointEstimates
from flockcal.solver.segments import SegmentedAccumulator
from flockcal.solver.slippage.monitor import SlipMonitor

log = logging.getLogger(__name__)

# Frames kept from before the first tree, to prime its monitor with (more than a baseline window needs).
PRIME_S = 12.0


class SlipWatch:
    """Watch the joints of a tree for slips and swaps while feeding the session's segmented accumulator.

    Frames go in `batch_s` micro-batches (whole ones: a shorter remainder waits for the next `feed`, or
    `flush`); after each, the watched joints are re-fitted on their post-slip segment where a slip was
    found, and the monitor sees those estimates. With no joints yet (`joints=None`, e.g. before the first
    live fit) frames go into the accumulator, and the last `PRIME_S` of them prime the first monitor (its
    baselines need not wait for frames after the tree). `watch(joints)` changes the tree; the monitor
    carries over what it knows of the joints the trees share, and works the new ones out from the frames
    it keeps.

    A monitor that raises is dropped for good (`failure` holds the exception) and the frames still reach
    the accumulator; `strict` re-raises it then (replays, where a failure is a bug), otherwise the caller
    reads `failure` (the live service, which must keep recording).
    """

    def __init__(self, joints, n_sensors: int, rate_hz: float, names=None, batch_s: float = 1 / 30,
                 segments: SegmentedAccumulator | None = None, strict: bool = True, **monitor_options):
        self.n_sensors = int(n_sensors)
        self.rate_hz = float(rate_hz)
        self.names = None if names is None else tuple(names)
        self.monitor_options = monitor_options
        self.segments = SegmentedAccumulator(n_sensors) if segments is None else segments
        # Whole frames, rounded down: a live refit at 1/batch_s only sees what the accumulator holds, and
        # 5 frames at 144 Hz moved it on 28.8 times a second.
        self.step = max(1, int(batch_s * rate_hz + 1e-9))
        self.strict = bool(strict)
        self.joints: np.ndarray | None = None
        self.monitor: SlipMonitor | None = None
        self.fits: JointEstimates | None = None  # the watched joints' latest refit (c, l)
        self.events: list = []  # every event found, across tree changes
        self.failure: BaseException | None = None
        self._held: tuple | None = None  # frames of an unfinished micro-batch (times, R, t, valid)
        self._before: list[tuple] = []  # frames from before the first tree (times, R, t, valid), PRIME_S of them
        if joints is not None:
            self.watch(joints)

    def watch(self, joints) -> bool:
        """Watch these (p, 2) (child, parent) joints from now on; True if the tree changed.

        The same joints in another order change nothing (the loop refits them itself). A changed tree
        goes to the monitor (`SlipMonitor.rejoint`): joints in both trees keep their baselines, segments
        and pending suspicions; new ones are worked out from the frames it keeps. The accumulator and
        its segments stay."""
        J = np.asarray(joints, dtype=int).reshape(-1, 2)
        if self.joints is not None and _same_joints(J, self.joints):
            return False
        if self.failure is not None:
            return False
        self.joints = J
        self.fits = None
        if not len(J):
            self.monitor = None
        elif self.monitor is not None:
            old = set(map(tuple, self.monitor.joints.tolist()))
            new = [tuple(r) for r in J.tolist() if tuple(r) not in old]
            self.monitor.rejoint(J)
            if self.names is not None:
                log.info("slip watch on a changed tree: %d joints kept, new %s", len(J) - len(new),
                         ", ".join(f"{self.names[a]}-{self.names[b]}" for a, b in new) or "none")
        else:
            self.monitor = SlipMonitor(J, self.n_sensors, self.rate_hz, self.names, **self.monitor_options)
            if self.names is not None:
                log.info("slip watch on %d joints: %s", len(J), ", ".join(f"{self.names[a]}-{self.names[b]}" for a, b in J))
            if self._before:
                self.monitor.prime(*(np.concatenate(x) for x in zip(*self._before)))
        self._before = []
        return True

    def feed(self, times, rotations, positions, valid=None, catch_up: int = 1) -> list:
        """Add frames; returns the events confirmed in the micro-batches completed by them.

        `catch_up` > 1 makes the micro-batches that many times longer (and the refits between them that
        many times fewer), for a live caller that has fallen behind its frames: the monitor still
        examines them `step_s` at a time. Replays and a live caller keeping up use 1, the measured cadence."""
        ts = np.atleast_1d(np.asarray(times, dtype=float))
        R = np.asarray(rotations, dtype=float)
        t = np.asarray(positions, dtype=float)
        v = np.ones(R.shape[:2], dtype=bool) if valid is None else np.asarray(valid, dtype=bool)
        if self._held is not None:
            ts, R, t, v = (np.concatenate([h, x]) for h, x in zip(self._held, (ts, R, t, v)))
            self._held = None
        if self.monitor is None:  # nothing to refit between batches: the accumulator takes them at once
            if len(ts):
                self.segments.ingest(ts, R, t, v)
                self._keep_before(ts, R, t, v)
            return []
        step = self.step * max(1, int(catch_up))
        whole = len(ts) - len(ts) % step
        if whole < len(ts):
            self._held = (ts[whole:], R[whole:], t[whole:], v[whole:])
        return self._batches(ts[:whole], R[:whole], t[:whole], v[:whole], step)

    def flush(self) -> list:
        """Run the held remainder as a short micro-batch (at the end of a take or session)."""
        if self._held is None:
            return []
        held, self._held = self._held, None
        if self.monitor is None:
            self.segments.ingest(*held)
            self._keep_before(*held)
            return []
        return self._batches(*held, len(held[0]))

    def _keep_before(self, ts, R, t, v) -> None:
        if self.failure is not None or self.joints is not None:
            return  # a failed monitor is not restarted; an empty tree has none to prime
        self._before.append((ts.copy(), R.copy(), t.copy(), v.copy()))
        while len(self._before) > 1 and ts[-1] - self._before[0][0][-1] > PRIME_S:
            self._before.pop(0)

    def _batches(self, ts, R, t, v, step: int) -> list:
        out = []
        for a in range(0, len(ts), step):
            sl = slice(a, a + step)
            self.segments.ingest(ts[sl], R[sl], t[sl], v[sl])
            if self.monitor is None:
                continue
            try:
                self.fits = self.segments.joint_estimates(self.joints)
                found = self.monitor.add_frames(ts[sl], R[sl], t[sl], v[sl], self.fits.c, self.fits.l)
                if found:
                    self.segments.apply(found)
            except Exception as exc:
                self.failure, self.monitor = exc, None
                if a + step < len(ts):
                    self.segments.ingest(ts[a + step:], R[a + step:], t[a + step:], v[a + step:])
                self.events += out
                if self.strict:
                    raise
                return out
            out += found
        self.events += out
        return out


def _same_joints(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether two (p, 2) joint lists hold the same (child, parent) rows, in any order."""
    return a.shape == b.shape and np.array_equal(np.unique(a, axis=0), np.unique(b, axis=0))
