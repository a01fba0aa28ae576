"""One session's live calibration: frames in, typed updates out. The accumulator (fed from one place),
the slip watch and the tree it watches, each joint's residual against the newest fit, and the session's
progress, in one object the live service drives from its pipeline thread (docs/server.md).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from flockcal.frames import Frames
from flockcal.solver.accumulator import GramAccumulator
from flockcal.solver.calibration import Calibration
from flockcal.solver.humanoid import HumanoidSample, Sample
from flockcal.solver.progress import Profile, Progress
from flockcal.solver.progress_tracker import ProgressTracker
from flockcal.solver.progress_words import done_change
from flockcal.solver.segments import SegmentedAccumulator
from flockcal.solver.slippage.monitor import SlipEvent, SwapEvent
from flockcal.solver.slippage.watch import SlipWatch

log = logging.getLogger(__name__)

# A fitted tree (automatic topology) must stay the fits' tree this long, in session time, before the slip
# loop watches it, the first one too: early fitted trees flicker, and a step on a wrong edge is no slip
# (early trees raised false events in the first seconds). Nothing is lost by waiting: the monitor keeps
# the joints both trees share and works new ones out from the frames it keeps (solver/slippage/watch.py).
TREE_SETTLE_S = 3.0


@dataclass(frozen=True)
class FitJoints:
    """The joints of one fit as arrays over its p joints, in the fit's order."""

    joints: tuple[tuple[str, str], ...]  # (child, parent) names
    pairs: np.ndarray  # (p, 2) sensor indices
    c: np.ndarray  # (p, 3) joint centre in the child's frame, metres
    l: np.ndarray  # (p, 3) in the parent's frame


def fit_joints(calibration: Calibration, names) -> FitJoints:
    """The joints of a fit as arrays, in its order (the order of its §5 dict's joints); sensors by index
    into `names` (the session's, which the fit was made with)."""
    pairs, c, l = calibration.joint_arrays()
    if tuple(calibration.names) != tuple(names):
        index = {n: i for i, n in enumerate(names)}
        pairs = np.array([[index[calibration.names[a]], index[calibration.names[b]]] for a, b in pairs.tolist()],
                         dtype=int).reshape(-1, 2)
    return FitJoints(
        joints=tuple((names[a], names[b]) for a, b in pairs.tolist()),
        pairs=np.asarray(pairs, dtype=int).reshape(-1, 2),
        c=np.asarray(c, dtype=float).reshape(-1, 3),
        l=np.asarray(l, dtype=float).reshape(-1, 3),
    )


@dataclass(frozen=True, eq=False)
class JointResiduals:
    """Each joint's residual rms over one sampling period, against the fit of its time."""

    time_s: float  # session clock of the sample's last frame
    joints: tuple[tuple[str, str], ...]  # (child, parent)
    rms_m: np.ndarray  # (p,) metres; NaN where no frame had both sensors valid


class ResidualSampler:
    """Residual rms per joint of the newest fit, one sample per `period` s of session time.

    A sample closes at the first frame at or after each boundary k·period of the session clock, and holds
    the frames since the previous one: every boundary the frames cross gives its sample, however the reader
    happened to hand them over (a loaded machine hands over fewer, larger batches; one sample per hand-over
    thinned the 20 Hz series to a few a second). Only a gap without frames gives none. Frames wait until a
    sample's worth has arrived: the cost of these small array steps is per call, and the reader hands
    frames over ~100 times a second."""

    def __init__(self, names, period: float):
        self.names = tuple(names)
        self.period = float(period)
        self._pending: list = []  # session frames (times, R, t, valid) not yet in a sample
        self._joints: tuple = ()
        self._sumsq = self._count = None
        self._cell: int | None = None  # floor(time / period) of the newest frame gathered
        self._emitted = -np.inf  # time of the newest sample
        self._time = 0.0
        self._joint_cache: tuple[Calibration, FitJoints] | None = None

    def joints(self, calibration: Calibration) -> FitJoints:
        """The fit's joints as arrays, worked out once per fit."""
        if self._joint_cache is None or self._joint_cache[0] is not calibration:
            self._joint_cache = (calibration, fit_joints(calibration, self.names))
        return self._joint_cache[1]

    def add(self, ts, R, t, valid, calibration: Calibration | None) -> list[JointResiduals]:
        self._pending.append((ts, R, t, valid))
        if self._pending[-1][0][-1] - self._pending[0][0][0] >= self.period:
            return self.drain(calibration)
        return []

    def drain(self, calibration: Calibration | None) -> list[JointResiduals]:
        """The frames waiting, against `calibration` (the newest fit): a sample for each period boundary
        they cross, the rest gathered towards the next."""
        pending, self._pending = self._pending, []
        if not pending or calibration is None or not len(calibration.joints):
            return []
        ts, R, t, valid = (np.concatenate([p[k] for p in pending]) for k in range(4))
        out = []
        fj = self.joints(calibration)
        if fj.joints != self._joints:
            out += self.flush()
            self._joints = fj.joints
            self._sumsq = np.zeros(len(fj.joints))
            self._count = np.zeros(len(fj.joints))
        ci, pj = fj.pairs[:, 0], fj.pairs[:, 1]
        e = (np.einsum("npab,pb->npa", R[:, ci], fj.c) + t[:, ci]
             - np.einsum("npab,pb->npa", R[:, pj], fj.l) - t[:, pj])
        sq = np.einsum("npa,npa->np", e, e)
        ok = valid[:, ci] & valid[:, pj] & np.isfinite(sq)
        sq = np.where(ok, sq, 0.0)
        # A frame closes a sample when it is the first past a boundary (a running max: a time that steps
        # back does not cross the same boundary twice).
        cells = np.floor(ts / self.period).astype(np.int64)
        reached = np.maximum.accumulate(np.concatenate([[cells[0] if self._cell is None else self._cell], cells]))
        ends = np.flatnonzero(reached[1:] > reached[:-1]) + 1  # each sample's frames end at its closing frame
        self._cell = int(reached[-1])
        # Running sums over the gathered sample (carried in as row 0) and the frames: a sample is the
        # difference of two.
        sumsq = np.cumsum(np.concatenate([np.zeros((1, len(sq[0]))), self._sumsq[None], sq]), axis=0)
        count = np.cumsum(np.concatenate([np.zeros((1, len(sq[0]))), self._count[None], ok]), axis=0)
        rows = np.concatenate([[0], ends + 1])
        s, c = sumsq[rows[1:]] - sumsq[rows[:-1]], count[rows[1:]] - count[rows[:-1]]
        for k, end in enumerate(ends.tolist()):  # per sample, not per frame: a few per call
            if c[k].any():
                rms = np.sqrt(np.maximum(s[k], 0.0) / np.maximum(c[k], 1))  # (a difference: never below 0)
                out.append(JointResiduals(float(ts[end - 1]), self._joints, np.where(c[k] > 0, rms, np.nan)))
                self._emitted = float(ts[end - 1])
        self._sumsq = sumsq[-1] - sumsq[rows[-1]]
        self._count = count[-1] - count[rows[-1]]
        self._time = float(ts[-1])
        return out

    def flush(self) -> list[JointResiduals]:
        """The sample being gathered (on a new tree, and at the session's end)."""
        if self._count is None or not self._count.any():
            return []
        rms = np.sqrt(self._sumsq / np.maximum(self._count, 1))
        sample = JointResiduals(self._time, self._joints, np.where(self._count > 0, rms, np.nan))
        self._sumsq[:] = 0
        self._count[:] = 0
        if self._time <= self._emitted:
            # Frames at the newest sample's instant (a loaded reader clamps late, back-dated frames to the
            # time before them) give no sample of their own: two at one time would make a page boundary
            # (`since`, exclusive) skip one.
            return []
        self._emitted = self._time
        return [sample]


@dataclass(frozen=True)
class DoneChange:
    """The session became calibrated ("calibrated") or stopped being so ("calibration_undone")."""

    action: str
    message: str
    time_s: float


@dataclass(frozen=True)
class FitInput:
    """What a refit on another thread needs: a copy of the accumulator, and when it was taken (session
    time, slip epoch: a fit begun before a slip cannot count that sensor's joints done again); the session's
    sample of frames (what the humanoid is found from) and its newest fit (whose humanoid is kept while the
    tree and the sample have not changed enough to matter)."""

    acc: GramAccumulator | SegmentedAccumulator
    time_s: float
    epoch: int
    sample: Sample | None = None
    previous: Calibration | None = None


@dataclass(frozen=True)
class LiveUpdate:
    """What one step of the live calibration gave, in the order the session should record it: `done`
    (before the slip events that undid it), `events`, then a slip watch that failed in this step."""

    events: tuple[SlipEvent | SwapEvent, ...] = ()
    residuals: tuple[JointResiduals, ...] = ()
    progress: Progress | None = None  # the new progress, when this step changed it
    done: DoneChange | None = None
    failure: BaseException | None = None  # the slip watch failed in this step (it watches no more)

    def __bool__(self) -> bool:
        return bool(self.events or self.residuals or self.progress is not None or self.failure is not None)


@dataclass
class _Step:
    events: list = field(default_factory=list)
    residuals: list = field(default_factory=list)
    progress: Progress | None = None
    done: DoneChange | None = None
    failure: BaseException | None = None

    def frozen(self) -> LiveUpdate:
        if not (self.events or self.residuals or self.progress is not None or self.failure is not None):
            return _NOTHING
        return LiveUpdate(tuple(self.events), tuple(self.residuals), self.progress, self.done, self.failure)


_NOTHING = LiveUpdate()


class LiveCalibration:
    """A session's calibration as frames arrive: `add_frames` (reader-time `Frames`), `fit_input` and
    `add_fit` around a refit made elsewhere, `finish` at the end, `add_final_fit` for the stored result.

    The session clock starts at its first frame (`t0`, reader time). The accumulator has one feeder: the
    slip watch when slips are watched (it refits between its micro-batches), else `add_frames` itself.
    Not thread-safe: one thread drives it; `t0` is written once and may be read from anywhere."""

    def __init__(self, names, rate_hz: float, profile: Profile, *, hierarchy=None, root: str | None = None,
                 skeleton=None, performer: str = "the performer", detect_slips: bool = True,
                 residual_period_s: float = 0.05):
        self.names = tuple(names)
        self.m = len(self.names)
        self.profile = profile
        self.performer = performer
        self.hierarchy, self.root, self.skeleton = hierarchy, root, skeleton  # what its fits are made with
        # A given tree (hierarchy or saved skeleton) cannot re-link: its joints need not wait to settle.
        self.tree_fixed = hierarchy is not None or skeleton is not None
        self.acc = SegmentedAccumulator(self.m) if detect_slips else GramAccumulator(self.m)
        self.watch = (SlipWatch(None, self.m, rate_hz, self.names, segments=self.acc, strict=False)
                      if detect_slips else None)
        self.tracker = ProgressTracker.for_profile(profile, tree_fixed=self.tree_fixed)
        self.residuals = ResidualSampler(self.names, residual_period_s)
        # A frame every 0.1 s of the session, at most 512 (then every 0.2 s, …): what the fit thread finds
        # the humanoid from (solver/humanoid.py), 0.85 MB for 16 sensors however long the session.
        self.sample = HumanoidSample(self.m)
        self.t0: float | None = None  # reader time of the session's first frame
        self.time_s = 0.0  # session time of the newest frame
        self.received = 0  # frames received
        self.calibration: Calibration | None = None  # the newest fit
        self.progress: Progress | None = None  # the newest progress; None before the first fit
        self.slip_epoch = 0  # slips applied to the accumulator so far
        self._fit_frames = 0  # accumulator frames the newest fit input held
        self._tree_candidate: tuple[frozenset, float] | None = None  # a fitted tree waiting to settle
        self._watched: tuple | None = None  # (the slip watch's joints array, its (child, parent) set)

    # --- frames ----------------------------------------------------------------------------------------
    def add_frames(self, frames: Frames, catch_up: int = 1) -> LiveUpdate:
        """Frames in reader time (invalid slots may hold anything): into the accumulator and the slip
        watch (`catch_up` > 1: longer micro-batches, for a caller behind its frames; SlipWatch.feed), then
        the residual sampling. Returns the slips confirmed, the progress they changed, the residual samples."""
        n = len(frames)
        if n == 0:
            return _NOTHING
        times = np.asarray(frames.times, dtype=float)
        valid = np.asarray(frames.valid, dtype=bool)
        if self.t0 is None:
            self.t0 = float(times[0])
        self.received += n
        R = np.where(valid[..., None, None], np.asarray(frames.rotations, dtype=float), 0.0)
        t = np.where(valid[..., None], np.asarray(frames.positions, dtype=float), 0.0)
        ts = times - self.t0
        self.time_s = float(ts[-1])
        self.sample.add(Frames(ts, R, t, valid))
        step = _Step()
        if self.watch is None:
            self.acc.ingest(ts, R, t, valid)
        else:
            had_failed = self.watch.failure is not None
            self._slips(self.watch.feed(ts, R, t, valid, catch_up), had_failed, step)
        step.residuals += self.residuals.add(ts, R, t, valid, self.calibration)
        return step.frozen()

    def finish(self) -> LiveUpdate:
        """The session's end: the slip watch's held remainder, the last residual sample."""
        step = _Step()
        if self.watch is not None:
            had_failed = self.watch.failure is not None
            self._slips(self.watch.flush(), had_failed, step)
        step.residuals += self.residuals.drain(self.calibration)
        step.residuals += self.residuals.flush()
        return step.frozen()

    def _slips(self, found: list, had_failed: bool, step: _Step) -> None:
        """The slip watch's events (it has opened the slipped sensors' segments): the epoch moves on, and
        the progress hears of them and is worked out again on the newest fit."""
        if found:
            self.slip_epoch += 1  # fits begun from here on see the new segments
            was_done = self.progress is not None and self.progress.done
            for ev in found:
                self.tracker.slip(ev, self.slip_epoch)
            if self.calibration is not None:
                self._progress(self.calibration, self.time_s, self.slip_epoch - 1, step, was_done)
            step.events += found
        if self.watch.failure is not None and not had_failed:
            step.failure = self.watch.failure

    # --- fits ------------------------------------------------------------------------------------------
    @property
    def frames(self) -> int:
        """Frames in the accumulator."""
        return self.acc.frames

    @property
    def fit_due(self) -> bool:
        """The accumulator holds frames the newest fit input did not."""
        return self.acc.frames > self._fit_frames

    def fit_input(self) -> FitInput:
        """A copy of the accumulator for a refit on another thread (frames keep flowing meanwhile)."""
        self._fit_frames = self.acc.frames
        return FitInput(self.acc.copy(), self.time_s, self.slip_epoch, self.sample.snapshot(), self.calibration)

    def add_fit(self, calibration: Calibration, time_s: float, epoch: int) -> LiveUpdate:
        """A refit of a `fit_input` taken at (`time_s`, `epoch`): its tree to the slip watch (a fitted
        tree once it has settled), its joints to the residuals, the progress."""
        self.calibration = calibration
        step = _Step()
        if self.watch is not None and len(calibration.joints):
            self._watch_tree(self.residuals.joints(calibration).pairs, time_s)
        self._progress(calibration, time_s, epoch, step)
        return step.frozen()

    def add_final_fit(self, calibration: Calibration) -> LiveUpdate:
        """The session's final fit (after `finish`): the progress as its stored result has it."""
        self.calibration = calibration
        step = _Step()
        self._progress(calibration, self.time_s, self.slip_epoch, step)
        return step.frozen()

    def _watch_tree(self, pairs: np.ndarray, time_s: float) -> None:
        """Hand the fit's tree to the slip watch: at once for a given tree, else once it has stayed the
        fits' tree for TREE_SETTLE_S (a tree that flickers back is never handed on)."""
        key = frozenset(map(tuple, pairs.tolist()))
        watched = self.watch.joints
        if watched is not None and (self._watched is None or self._watched[0] is not watched):
            self._watched = (watched, frozenset(map(tuple, watched.tolist())))
        if watched is not None and key == self._watched[1]:
            # The tree watched already (nearly every refit): `watch` would find no change, at the cost of
            # comparing the two lists in numpy 30 times a second.
            self._tree_candidate = None
            return
        if self.tree_fixed:
            self._tree_candidate = None
            self.watch.watch(pairs)
            return
        if self._tree_candidate is None or self._tree_candidate[0] != key:
            self._tree_candidate = (key, time_s)
        elif time_s - self._tree_candidate[1] >= TREE_SETTLE_S:
            self._tree_candidate = None
            self.watch.watch(pairs)

    def _progress(self, fit: Calibration, time_s: float, epoch: int, step: _Step,
                  was_done: bool | None = None) -> None:
        """Fold a fit into the progress; becoming done (or undone) is news of its own."""
        if was_done is None:
            was_done = self.progress is not None and self.progress.done
        try:
            self.progress = self.tracker.add_fit(fit, time_s, epoch)
        except (KeyError, TypeError, ValueError) as exc:  # a malformed fit must not stop the session
            log.warning("progress not updated: %s", exc)
            return
        step.progress = self.progress
        change = done_change(self.progress, was_done, self.performer, self.profile, time_s)
        if change is not None:
            step.done = DoneChange(change[0], change[1], time_s)
