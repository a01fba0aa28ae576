"""The live pipeline: frames from the reader thread → the session's accumulator → fits → snapshots.

One thread owns all mutable state. The reader only appends to a pending list; the pipeline wakes when
frames arrive (at most `publish_hz` times a second), folds them into the live session's Gram
accumulator and frame log, refits at `fit_hz`, and publishes an immutable Snapshot by swapping one
reference. Nothing here ever waits for a client.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from flockcal.errors import FlockcalError
from flockcal.server.framelog import FrameLog
from flockcal.server.progress import ProgressTracker, default_target, waiting
from flockcal.server.snapshot import ResidualSample, Snapshot
from flockcal.server.store import Store
from flockcal.threads import name_os_thread

log = logging.getLogger(__name__)

RECENT_EVENTS = 200
SLIP_FIELDS = ("time_s", "sensor", "candidates", "joints", "jump_mm", "confidence", "detected_s")
RECENT_RESIDUALS = 400


@dataclass
class LiveSession:
    """Mutable state of the session being recorded; touched only by the pipeline thread."""

    id: str
    performer: str
    names: tuple[str, ...]
    hierarchy: dict | None
    root: str | None
    framelog: FrameLog
    skeleton: object = None  # a saved Skeleton: topology and bones fixed, only placements are fitted
    acc: object = None  # GramAccumulator, made on install
    t0: float | None = None  # reader time of the session's first frame
    frames: int = 0
    started_wall: float = field(default_factory=time.time)
    fit: dict | None = None
    fit_error: str | None = None
    fit_frames: int = 0  # accumulator frames the newest fit used
    slip_monitor: object = None
    residual_rows: list = field(default_factory=list)  # (time_s, {joint: mm}) not yet in the store
    tracker: ProgressTracker | None = None  # the session's progress, made on install
    progress: dict | None = None  # its newest document (server/progress.py); None before the first fit
    slip_epoch: int = 0  # slips applied to the accumulator so far: fits carry the epoch they were begun in

    def summary(self) -> dict:
        return {
            "id": self.id, "performer": self.performer, "state": "live", "frames": self.frames,
            "started_at": self.started_wall,
            "hierarchy": self.hierarchy, "root": self.root,
            "known_skeleton": self.skeleton is not None,
            "progress": self.progress["progress"] if self.progress else 0.0,
            "done": bool(self.progress and self.progress["done"]),
        }


def _finite(obj):
    """JSON-safe copy: NaN and ±inf become None (browsers cannot parse them), numpy scalars become floats."""
    kind = type(obj)
    if kind is float:  # the common leaves first, by exact type: most of the cost is the walk itself
        return obj if math.isfinite(obj) else None
    if kind is str or kind is int or kind is bool or obj is None:
        return obj
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(obj) else None
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    return obj


def calibrate_dict(acc, names, hierarchy=None, root=None, skeleton=None, tolerance: float = 0.005) -> dict:
    """The §5 JSON of a fit of `acc` (solver's calibrate), JSON-safe; SolverError etc. propagate.

    A SegmentedAccumulator fits joints of slipped sensors on the frames since their slip. With a saved
    `skeleton` only the sensor placements are fitted (its tree and bones are kept)."""
    from flockcal.solver.calibration import calibrate

    if skeleton is not None:
        return known_dict_of(skeleton, acc, names)[0]
    # The solver builds these dicts JSON-safe (Calibration.to_dict: Python scalars, None for NaN; the tests
    # hold it to that), so they are not walked again: this runs ~30×/s, and the walk cost as much as the MST.
    if hasattr(acc, "calibration_dict"):
        return acc.calibration_dict(hierarchy=hierarchy, root=root, names=list(names), tolerance=tolerance)
    return calibrate(acc, hierarchy=hierarchy, root=root, names=list(names), tolerance=tolerance).to_dict()


def known_dict_of(skeleton, acc, names, previous=None) -> tuple[dict, object]:
    """(JSON-safe §5 dict, KnownFit) of a fit with a saved skeleton; `previous` KnownFit warm-starts it."""
    from flockcal.server.skeletons import known_dict, known_fit

    fit = known_fit(skeleton, acc, names, previous)
    return _finite(known_dict(fit, acc, list(names))), fit


def new_accumulator(m: int, segmented: bool = False):
    """The session's accumulator; segmented ones can restart a slipped sensor's joints (design.md §4)."""
    if segmented:
        try:
            from flockcal.solver.segments import SegmentedAccumulator

            return SegmentedAccumulator(m)
        except ImportError:
            pass
    from flockcal.solver.accumulator import GramAccumulator

    return GramAccumulator(m)


def accumulate(acc, times, rotations, positions, valid) -> None:
    if hasattr(acc, "whole"):
        acc.update(times, rotations, positions, valid)
    else:
        acc.update(rotations, positions, valid)


def fit_copy(acc):
    """A copy that a fit on another thread can read while `acc` keeps growing (cheap: 4m×4m matrices)."""
    if not hasattr(acc, "whole"):
        return acc.copy()
    # A SegmentedAccumulator: its segments' base snapshots never change, only `whole` grows.
    clone = object.__new__(type(acc))
    clone.__dict__.update(acc.__dict__)
    clone.whole = acc.whole.copy()
    clone.segments = dict(acc.segments)
    clone.history = list(acc.history)
    clone._snaps = type(acc._snaps)(maxlen=acc._snaps.maxlen)
    return clone


class Pipeline:
    """Owns the live state; `feed` and `tracker_event` may be called from any thread."""

    def __init__(
        self,
        names: tuple[str, ...],
        store: Store,
        source_status: Callable[[], dict],
        publish_hz: float = 60.0,
        fit_hz: float = 30.0,
        residual_hz: float = 20.0,
        on_publish: Callable[[Snapshot], None] | None = None,
        detect_slips: bool = True,
        rate_hz: Callable[[], float] | None = None,
        tolerance: float = 0.005,
        target: float | None = None,
    ):
        self.names = tuple(names)
        self.tolerance = float(tolerance)
        # The joint-centre error at which a joint counts as calibrated (progress, done): at most the tolerance.
        self.target = default_target(self.tolerance) if target is None else float(target)
        self.m = len(self.names)
        self.store = store
        self.source_status = source_status
        self.min_publish_s = 1.0 / publish_hz
        self.min_fit_s = 1.0 / fit_hz
        self.residual_period = 1.0 / residual_hz
        self.on_publish = on_publish
        self.detect_slips = detect_slips
        self.rate_hz = rate_hz or (lambda: 144.0)
        self._cond = threading.Condition()
        self._pending: list[tuple] = []
        self._pending_events: list[dict] = []
        self._commands: list[tuple[Callable, Future]] = []
        self._stop = False
        self._thread: threading.Thread | None = None
        # State below is only touched by the pipeline thread.
        self.live: LiveSession | None = None
        self.frames = 0
        self.last_frame_time: float | None = None
        self._R = np.tile(np.eye(3), (self.m, 1, 1))
        self._t = np.zeros((self.m, 3))
        self._valid = np.zeros(self.m, dtype=bool)
        self._have_pose = False
        self._fit_seq = 0
        self._seq = 0
        self._events: deque = deque(maxlen=RECENT_EVENTS)
        self._residuals: deque = deque(maxlen=RECENT_RESIDUALS)
        self._residual_seq = 0
        self._res_sumsq = None
        self._res_count = None
        self._res_joints: tuple = ()
        self._res_last_emit: float | None = None
        self._res_pending: list = []  # session frames (times, R, t, valid) not yet in a residual sample
        self._last_fit_time = 0.0
        self._fit_cond = threading.Condition()
        self._joint_cache = None
        self._slip_batch: list = []
        self.slip_batch_s = 0.1
        self._fit_job = None
        self._fit_done = None
        self._fit_busy = False
        self._fit_thread: threading.Thread | None = None
        self._known_prev = None  # (session id, KnownFit): the fit thread's warm start
        self._last_db_flush = 0.0
        self.pose_fit: dict | None = None
        self.fits_done = 0
        self.fit_seconds = 0.0
        self._last_status: dict = {}
        self._snapshot = self._make_snapshot()

    # --- called from other threads -----------------------------------------------------------------
    @property
    def snapshot(self) -> Snapshot:
        return self._snapshot

    def feed(self, times, rotations, positions, valid) -> None:
        """Reader callback: hand over a batch of frames (arrays over n frames); never blocks for long."""
        with self._cond:
            self._pending.append((times, rotations, positions, valid))
            if len(self._pending) == 1:  # later batches find the pipeline already counting down to publish
                self._cond.notify()

    def tracker_event(self, event: dict) -> None:
        with self._cond:
            self._pending_events.append(event)
            self._cond.notify()

    def add_event(self, event: dict) -> None:
        """Queue an event (slip, session, tracker) for the store and the websocket."""
        self.tracker_event(event)

    def call(self, fn: Callable[[], object], timeout: float = 30.0):
        """Run `fn` on the pipeline thread after the frames already received, and return its result."""
        fut: Future = Future()
        with self._cond:
            self._commands.append((fn, fut))
            self._cond.notify()
        if self._thread is None or not self._thread.is_alive():
            raise FlockcalError("the live pipeline is not running; restart the service")
        return fut.result(timeout)

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="flockcal-pipeline", daemon=True)
        self._fit_thread = threading.Thread(target=self._fit_worker, name="flockcal-fit", daemon=True)
        self._thread.start()
        self._fit_thread.start()

    def stop(self) -> None:
        with self._cond:
            self._stop = True
            self._cond.notify()
        with self._fit_cond:
            self._fit_cond.notify()
        for thread in (self._thread, self._fit_thread):
            if thread:
                thread.join(10)

    # --- session control (run on the pipeline thread through `call`) ----------------------------------
    def begin_session(self, live: LiveSession) -> None:
        def install():
            if self.live is not None:
                raise FlockcalError(f"session {self.live.id} is still live")
            live.acc = new_accumulator(self.m, segmented=self.detect_slips)
            # A given tree (hierarchy or saved skeleton) cannot re-link, so its joints need not wait for it to settle.
            live.tracker = ProgressTracker(self.target, self.tolerance,
                                           tree_fixed=live.hierarchy is not None or live.skeleton is not None)
            self.live = live
            self._reset_residuals()
            self._residuals.clear()
            self._publish()

        self.call(install)

    def end_session(self) -> tuple[LiveSession, dict | None, str | None]:
        """Stop recording; returns (session, final fit dict or None, why there is no fit)."""

        def finish():
            live = self.live
            if live is None:
                raise FlockcalError("no session is live")
            self._drain_residuals()
            self._flush_residual_sample(force=True)
            self._flush_db()
            result, error = None, None
            if live.acc.frames > 0:
                try:
                    result = calibrate_dict(live.acc, self.names, live.hierarchy, live.root, live.skeleton,
                                            self.tolerance)
                    slips = [{k: e[k] for k in SLIP_FIELDS if k in e}
                             for e in self.store.events(live.id, limit=100_000) if e["type"] == "slip"]
                    if slips:
                        result["slip_events"] = slips
                    # What the session had reached, as the stored result has it (done joints stay done).
                    self._progress_step(live, result, self._session_time(live), live.slip_epoch)
                except FlockcalError as exc:
                    error = str(exc)
            else:
                error = "no frames arrived during the session"
            live.framelog.close()
            self.live = None
            if result:
                self.pose_fit = result
            self._publish()
            return live, result, error

        return self.call(finish)

    # --- the thread ----------------------------------------------------------------------------------
    def _run(self) -> None:
        name_os_thread("fc-pipeline")
        last_publish = 0.0
        while True:
            with self._cond:
                while not self._stop and not self._commands:
                    has_work = bool(self._pending or self._pending_events or self._fit_done)
                    # Publish as soon as frames arrive, but no more than publish_hz; status twice a second.
                    due = last_publish + (self.min_publish_s if has_work else 0.5)
                    now = time.monotonic()
                    if now >= due:
                        break
                    self._cond.wait(due - now)
                stopping = self._stop
                batches, self._pending = self._pending, []
                events, self._pending_events = self._pending_events, []
                commands, self._commands = self._commands, []
            try:
                if batches:
                    self._process_frames(batches)
                if events:
                    self._process_events(events)
                for fn, fut in commands:
                    try:
                        fut.set_result(fn())
                    except BaseException as exc:  # handed back to the caller
                        fut.set_exception(exc)
                self._publish()
            except Exception:  # the pipeline must survive a bad batch; the log says why
                log.exception("pipeline step failed")
            last_publish = time.monotonic()
            if stopping:
                if self.live is not None:
                    self._flush_db()
                    self.live.framelog.flush()
                return

    def _process_frames(self, batches: list[tuple]) -> None:
        if len(batches) == 1:
            times, R, t, valid = batches[0]
        else:
            times = np.concatenate([b[0] for b in batches])
            R = np.concatenate([b[1] for b in batches])
            t = np.concatenate([b[2] for b in batches])
            valid = np.concatenate([b[3] for b in batches])
        times = np.asarray(times, dtype=float)
        R = np.asarray(R, dtype=float)
        t = np.asarray(t, dtype=float)
        valid = np.asarray(valid, dtype=bool)
        n = len(times)
        if n == 0:
            return
        self.frames += n
        self.last_frame_time = float(times[-1])
        # Newest pose of each sensor, held from its last valid record.
        any_valid = valid.any(axis=0)
        if any_valid.any():
            last = n - 1 - np.argmax(valid[::-1], axis=0)
            cols = np.flatnonzero(any_valid)
            self._R[cols] = R[last[cols], cols]
            self._t[cols] = t[last[cols], cols]
            self._have_pose = True
        self._valid = valid[-1].copy()
        live = self.live
        if live is None:
            return
        if live.t0 is None:
            live.t0 = float(times[0])
        live.framelog.write(times, R, t, valid)
        live.frames += n
        limits = getattr(self, "limits", None)  # issue #16: session length, free disk (server/limits.py)
        if limits is not None:
            limits.check(live.id, float(times[-1]) - live.t0)
        Rz = np.where(valid[..., None, None], R, 0.0)
        tz = np.where(valid[..., None], t, 0.0)
        accumulate(live.acc, times - live.t0, Rz, tz, valid)
        # Residual samples come out residual_hz times a second, so work them out once per sample rather
        # than once per reader hand-over (~100/s): the cost of these small array steps is per call.
        self._res_pending.append((times - live.t0, Rz, tz, valid))
        if self._res_pending[-1][0][-1] - self._res_pending[0][0][0] >= self.residual_period:
            self._drain_residuals()

    def _drain_residuals(self) -> None:
        pending, self._res_pending = self._res_pending, []
        if pending:
            self._residual_step(*(np.concatenate([p[k] for p in pending]) for k in range(4)))

    def _joint_arrays(self, fit: dict):
        """(joints ((child, parent) names), pairs (p,2), c (p,3), l (p,3)) of a fit, cached per fit."""
        if self._joint_cache is not None and self._joint_cache[0] is fit:
            return self._joint_cache[1]
        index = {n: i for i, n in enumerate(self.names)}
        joints = tuple((j["child"], j["parent"]) for j in fit["joints"])
        pairs = np.array([[index[c], index[p]] for c, p in joints], dtype=int).reshape(-1, 2)
        c = np.array([j["c"] for j in fit["joints"]], dtype=float).reshape(-1, 3)
        l = np.array([j["l"] for j in fit["joints"]], dtype=float).reshape(-1, 3)
        out = (joints, pairs, c, l)
        self._joint_cache = (fit, out)
        return out

    def _residual_step(self, ts, R, t, valid) -> None:
        live = self.live
        fit = live.fit
        if not fit or not fit.get("joints"):
            return
        joints, pairs, c, l = self._joint_arrays(fit)
        if joints != self._res_joints:
            self._flush_residual_sample(force=True)
            self._res_joints = joints
            self._res_sumsq = np.zeros(len(joints))
            self._res_count = np.zeros(len(joints))
            live.slip_monitor = self._new_slip_monitor(pairs)
            self._slip_batch = []
        ci, pj = pairs[:, 0], pairs[:, 1]
        e = (np.einsum("npab,pb->npa", R[:, ci], c) + t[:, ci]
             - np.einsum("npab,pb->npa", R[:, pj], l) - t[:, pj])
        sq = np.einsum("npa,npa->np", e, e)
        ok = valid[:, ci] & valid[:, pj] & np.isfinite(sq)
        sq = np.where(ok, sq, 0.0)
        self._res_sumsq += sq.sum(axis=0)
        self._res_count += ok.sum(axis=0)
        self._res_time = float(ts[-1])
        if self._res_last_emit is None:
            self._res_last_emit = float(ts[0])
        if self._res_time - self._res_last_emit >= self.residual_period:
            self._flush_residual_sample()
        if live.slip_monitor is not None and np.isfinite(c).all() and np.isfinite(l).all():
            # The monitor's cost is mostly per call: feed it every slip_batch_s, not every micro-batch.
            self._slip_batch.append((ts, R, t, valid))
            if ts[-1] - self._slip_batch[0][0][0] >= self.slip_batch_s:
                batch, self._slip_batch = self._slip_batch, []
                self._slip_step(*(np.concatenate([b[k] for b in batch]) for k in range(4)), c, l)

    def _new_slip_monitor(self, pairs):
        if not self.detect_slips:
            return None
        try:
            from flockcal.solver.slippage import SlipMonitor
        except ImportError:
            return None
        rate = self.rate_hz()
        try:
            return SlipMonitor(pairs, self.m, rate, self.names)
        except FlockcalError as exc:
            log.warning("slip monitor unavailable: %s", exc)
            return None

    def _slip_step(self, ts, R, t, valid, c, l) -> None:
        live = self.live
        try:
            found = live.slip_monitor.update(ts, R, t, valid, c, l)
        except Exception as exc:  # detection is advisory: a failure must not stop the session
            log.warning("slip monitor failed, disabling it for this session: %s", exc)
            live.slip_monitor = None
            return
        if found and hasattr(live.acc, "apply"):
            try:
                live.acc.apply(found)  # the slipped sensor's joints refit on frames since the slip
            except Exception as exc:
                log.warning("could not open a segment after the slip: %s", exc)
        events = []
        for ev in found or []:
            d = ev.to_dict() if hasattr(ev, "to_dict") else dict(ev)
            d["type"] = d.pop("kind", "slip")
            events.append(_finite(d))
        if events:
            live.slip_epoch += 1  # fits begun from here on see the new segments
            was_done = bool(live.progress and live.progress["done"])
            for d in events:
                live.tracker.slip(d, live.slip_epoch)
            if live.fit is not None:
                self._progress_step(live, live.fit, self._session_time(live), live.slip_epoch - 1, was_done)
            self._process_events(events)

    def _flush_residual_sample(self, force: bool = False) -> None:
        if self._res_count is None or not self._res_count.any() or self.live is None:
            return
        rms = np.sqrt(self._res_sumsq / np.maximum(self._res_count, 1)) * 1000.0
        values = {j[0]: round(float(v), 4) for j, v, c in zip(self._res_joints, rms, self._res_count) if c > 0}
        self._residual_seq += 1
        sample = ResidualSample(self._residual_seq, self._res_time, values)
        self._residuals.append(sample)
        self.live.residual_rows.append((sample.time_s, values))
        self._res_sumsq[:] = 0
        self._res_count[:] = 0
        self._res_last_emit = self._res_time

    def _reset_residuals(self) -> None:
        self._res_pending = []
        self._res_joints = ()
        self._res_sumsq = self._res_count = None
        self._res_last_emit = None

    def _process_events(self, events: list[dict]) -> None:
        live = self.live
        rows = []
        for ev in events:
            ev = dict(ev)
            ev.setdefault("wall_time", time.time())
            if live is not None and "session_id" not in ev:
                ev["session_id"] = live.id
                if "time_s" not in ev:
                    ev["time_s"] = (self.last_frame_time - live.t0) if (live.t0 is not None and self.last_frame_time is not None) else 0.0
            rows.append(ev)
        ids = self.store.add_events(rows)
        for ev, i in zip(rows, ids):
            ev["id"] = i
            self._events.append(ev)

    def _flush_db(self) -> None:
        live = self.live
        if live is None:
            return
        rows, live.residual_rows = live.residual_rows, []
        self.store.add_residuals(live.id, rows)
        self.store.update_session(live.id, frames=live.frames)
        self._last_db_flush = time.monotonic()

    def _publish(self) -> None:
        live = self.live
        now = time.monotonic()
        if live is not None:
            if now - live.framelog.last_flush >= live.framelog.flush_s:
                live.framelog.flush()
            if now - self._last_db_flush >= 1.0:
                self._flush_db()
            self._take_fit(live)
            if (not self._fit_busy and live.acc.frames > live.fit_frames
                    and now - self._last_fit_time >= self.min_fit_s):
                # Hand a copy of the Gram matrix to the fit thread; frames keep flowing meanwhile.
                self._fit_busy = True
                # Keep a fixed grid (not "period after the last start") so the rate holds at fit_hz.
                self._last_fit_time = max(self._last_fit_time + self.min_fit_s, now - self.min_fit_s)
                live.fit_frames = live.acc.frames
                stamp = (self._session_time(live), live.slip_epoch)
                with self._fit_cond:
                    self._fit_job = (live.id, fit_copy(live.acc), live.hierarchy, live.root, live.skeleton, stamp)
                    self._fit_cond.notify()
        self._snapshot = self._make_snapshot()
        if self.on_publish is not None:
            self.on_publish(self._snapshot)

    def _take_fit(self, live: LiveSession) -> None:
        with self._cond:
            done, self._fit_done = self._fit_done, None
        if done is None:
            return
        session_id, fit, error, seconds, (time_s, epoch) = done
        self.fits_done += 1
        self.fit_seconds += seconds
        if session_id != live.id:
            return
        if fit is not None:
            live.fit = fit
            live.fit_error = None
            self.pose_fit = fit
            self._fit_seq += 1
            self._progress_step(live, fit, time_s, epoch)
        else:
            live.fit_error = error

    def _session_time(self, live: LiveSession) -> float:
        if live.t0 is None or self.last_frame_time is None:
            return 0.0
        return self.last_frame_time - live.t0

    def _progress_step(self, live: LiveSession, fit: dict, time_s: float, epoch: int,
                       was_done: bool | None = None) -> None:
        """Fold a fit into the session's progress; becoming done (or undone) is an event of its own."""
        if was_done is None:
            was_done = bool(live.progress and live.progress["done"])
        try:
            live.progress = live.tracker.update(fit, time_s, epoch)
        except (KeyError, TypeError, ValueError) as exc:  # a malformed fit must not stop the pipeline
            log.warning("progress not updated: %s", exc)
            return
        done = live.progress["done"]
        if done and not was_done:
            n = live.progress["joints_needed"]
            self._process_events([{
                "type": "session", "session_id": live.id, "action": "calibrated", "time_s": time_s,
                "message": f"{live.performer} is calibrated: all {n} joints pinned to "
                           f"{1000 * self.target:.1f} mm after {time_s:.1f} s"}])
        elif was_done and not done:
            why = next((m["why"] for m in live.progress["missing"] if m.get("undone")), None)
            if why is None and live.progress["missing"]:
                why = f"{live.progress['missing'][0]['label']}: {live.progress['missing'][0]['why']}"
            self._process_events([{
                "type": "session", "session_id": live.id, "action": "calibration_undone", "time_s": time_s,
                "message": f"{live.performer} is no longer calibrated: {why or 'a joint was undone'}"}])

    def _fit_worker(self) -> None:
        """Refits on its own thread, so a slow fit never delays frames or snapshots."""
        name_os_thread("fc-fit")
        while True:
            with self._fit_cond:
                while self._fit_job is None and not self._stop:
                    self._fit_cond.wait()
                if self._stop:
                    return
                job, self._fit_job = self._fit_job, None
            session_id, acc, hierarchy, root, skeleton, stamp = job
            start = time.perf_counter()
            fit, error = None, None
            try:
                if skeleton is not None:
                    # Start from this session's last known-skeleton fit: one or two Gauss–Newton steps.
                    prev = self._known_prev[1] if self._known_prev and self._known_prev[0] == session_id else None
                    fit, known = known_dict_of(skeleton, acc, self.names, prev)
                    self._known_prev = (session_id, known)
                else:
                    fit = calibrate_dict(acc, self.names, hierarchy, root, tolerance=self.tolerance)
            except FlockcalError as exc:
                error = str(exc)
            except Exception as exc:  # a numerical failure must not stop the service
                log.exception("fit failed")
                error = f"fit failed: {exc}"
            with self._cond:
                self._fit_done = (session_id, fit, error, time.perf_counter() - start, stamp)
                self._fit_busy = False
                self._cond.notify()

    def _make_snapshot(self) -> Snapshot:
        self._seq += 1
        live = self.live
        try:
            tracker = dict(self.source_status())
        except Exception as exc:  # the status of a source that failed is itself news
            tracker = {"connected": False, "last_error": f"status unavailable: {exc}"}
        session = None
        progress = None
        if live is not None:
            session = live.summary()
            session["time_s"] = self._session_time(live)
            session["fit_error"] = live.fit_error
            progress = live.progress or waiting(self.names, self.target, live.fit_error or "no fit yet: keep moving")
        status = dict(tracker)
        status.update(
            frames=self.frames,
            session=session,
            sensors=list(self.names),
            fits=self.fits_done,
            fit_ms=round(1000 * self.fit_seconds / self.fits_done, 3) if self.fits_done else None,
        )
        return Snapshot(
            seq=self._seq,
            wall_time=time.time(),
            frames=self.frames,
            last_frame_time=self.last_frame_time,
            status=status,
            session=session,
            names=self.names,
            fit=live.fit if live is not None else None,
            fit_seq=self._fit_seq,
            residuals=tuple(self._residuals),
            events=tuple(self._events),
            rotations=self._R.copy() if self._have_pose else None,
            positions=self._t.copy() if self._have_pose else None,
            valid=self._valid.copy(),
            pose_fit=self.pose_fit,
            progress=progress,
        )
