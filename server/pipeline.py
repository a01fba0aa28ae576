"""The live pipeline, a scheduler: frames from the reader thread → the session's live calibration
(solver/live.py: accumulator, slip watch, residuals, progress) → refits on the fit thread → snapshots.

One thread ("fc-pipeline") runs it and owns the live state: `Ingest` (newest pose, frame count), the
session's `LiveCalibration`, `Persistence` (store, frame log), `SnapshotMaker`. `FitWorker` refits on its
own thread. The reader only appends to a queue; the event loop only reads the newest immutable Snapshot.
What the calibration returns is typed; it becomes JSON at the store and the snapshots. See docs/server.md.
"""

from __future__ import annotations

import logging
import math
import threading
from concurrent.futures import Future
from dataclasses import replace
from typing import Callable

from flockcal.drivers.reader import TrackerEvent
from flockcal.errors import FlockcalError
from flockcal.frames import Frames
from flockcal.server.clock import ServiceClock
from flockcal.server.fitting import FitJob, FitView, FitWorker, solve_fit
from flockcal.server.ingest import Ingest
from flockcal.server.limits import LimitStop, SessionLimits
from flockcal.server.live_session import LiveSession
from flockcal.server.events import Event
from flockcal.server.persistence import Persistence, slip_event
from flockcal.server.snapshot import Snapshot, SnapshotMaker, SourceStatus
from flockcal.server.sources import tracker_event
from flockcal.server.store import Store
from flockcal.solver.calibration import Calibration
from flockcal.solver.live import LiveCalibration, LiveUpdate
from flockcal.threads import name_os_thread

__all__ = ["LiveSession", "Pipeline"]

log = logging.getLogger(__name__)

# Behind the tracker by more than this, with more frames waiting, the pipeline catches up before it
# hands out a refit: the slip loop's events wait for the catch-up, a refit (progress, the tree) can
# wait for the next one, and the fit thread would take CPU and the GIL from it on a starved machine.
BEHIND_S = 0.3
# ... but no longer than this between refits: on a machine starved for good the pipeline never caught up,
# and no fit was handed out for minutes (a profile at load 10 found the fit thread idle; progress and the
# dashboard's fit stood still, and a test reading fit messages timed out).
BEHIND_FIT_S = 0.5
# How much longer the slip loop's micro-batches get while catching up: 0.1 s (the monitor's own step)
# when behind, 1/3 s when over FAR_BEHIND_S behind (then c, l are at most 1/3 s stale; they move slowly).
CATCH_UP, FAR_BEHIND_S, FAR_CATCH_UP = 3, 1.0, 10
# At most this many seconds of a backlog of frames per step, then a snapshot: on a starved machine a
# whole backlog in one step left every client without a message for 30 s (a benchmark's websocket timed
# out at load 11 on 2 cores); the snapshots then show the lag instead of going silent.
MAX_STEP_S = 1.0


def _step_of(pending: list[Frames], frames: float) -> tuple[list[Frames], list[Frames]]:
    """(the first batches, at least one, holding at most `frames` frames; the rest)."""
    total, k = 0, 0
    while k < len(pending) and (k == 0 or total + len(pending[k]) <= frames):
        total += len(pending[k])
        k += 1
    return pending[:k], pending[k:]


class Pipeline:
    """Schedules the live work; `feed`, `tracker_event`, `add_event` and `call` may be called from any thread.

    Threads: `_cond` guards the hand-over queue (`_pending`, `_pending_events`, `_commands`) and `_stop`,
    and nothing else; every other field, and every part but the fit worker, belongs to the pipeline
    thread (`_run`, and the functions it runs through `call`). The fit worker guards its own slots with
    its own lock; the only order ever taken is `_cond` → the fit worker's lock."""

    def __init__(
        self,
        names: tuple[str, ...],
        store: Store,
        source_status: Callable[[], SourceStatus],
        publish_hz: float = 60.0,
        fit_hz: float = 30.0,
        residual_hz: float = 20.0,
        on_publish: Callable[[Snapshot], None] | None = None,
        detect_slips: bool = True,
        rate_hz: Callable[[], float] | None = None,
        tolerance: float = 0.005,
        target: float = 0.005 / 2 ** 0.5,
        limits: SessionLimits | None = None,
        clock: ServiceClock | None = None,
    ):
        self.names = tuple(names)
        self.m = len(self.names)
        self.min_publish_s = 1.0 / publish_hz
        self.min_fit_s = 1.0 / fit_hz
        self.residual_s = 1.0 / residual_hz
        self.on_publish = on_publish
        self.limits = limits  # session length, free disk (server/limits.py)
        # Stamps on events and snapshots (never stepping back: server/clock.py).
        self.clock = clock if clock is not None else ServiceClock()
        self.detect_slips = detect_slips
        self.rate_hz = rate_hz or (lambda: 144.0)
        self._cond = threading.Condition()
        self._pending: list[Frames] = []
        self._pending_events: list[TrackerEvent | Event] = []
        self._commands: list[tuple[Callable, Future, int]] = []  # (fn, its future, frames before it)
        self._stop = False
        self._thread: threading.Thread | None = None
        # Work that rides on this thread's steps (the live streams' `Outputs.hand_over`), given at `start`:
        # run at each step, and again when the time it returned comes with no step before it.
        self._beside: Callable[[], float] | None = None
        self._beside_due = math.inf
        # The session manager's side, given at `start`: stop a session for a limit, store held row updates.
        self._stop_session: Callable[[LimitStop], None] = lambda stop: None
        self._flush_held_rows: Callable[[], bool] = lambda: True
        # The parts, and the state below, belong to the pipeline thread.
        self.ingest = Ingest(self.m)
        self.persistence = Persistence(store, self.clock, on_storage_failed=self._storage_failed)
        self.fitter = FitWorker(self.names, tolerance, self.clock, on_done=self._wake)
        self.snapshots = SnapshotMaker(self.names, source_status, target, stamp=self.clock.stamp)
        self.live: LiveSession | None = None
        self.pose_fit: Calibration | None = None  # the fit the live skeleton is drawn with
        # Whose fit that is: (session id, fit_seq), fit_seq None for a stopped session's final (stored) fit;
        # the pose's `rig` carries it so a page knows which /gltf rig the stream drives.
        self.pose_fit_id: tuple[str, int | None] | None = None
        self._fit_seq = 0
        self._last_fit_time = 0.0
        first = self._make_snapshot()
        if self.on_publish is not None:
            self.on_publish(first)

    # --- called from other threads -----------------------------------------------------------------
    @property
    def snapshot(self) -> Snapshot:
        return self.snapshots.current

    @property
    def fits_done(self) -> int:
        return self.fitter.fits_done

    def feed(self, frames: Frames) -> None:
        """Reader callback: hand over a batch of frames; never blocks for long."""
        with self._cond:
            self._pending.append(frames)
            if len(self._pending) == 1:  # later batches find the pipeline already counting down to publish
                self._cond.notify()

    def tracker_event(self, event: TrackerEvent) -> None:
        """The source's callback for tracker news (its own thread): queued as it came, typed."""
        self._queue_event(event)

    def add_event(self, event: Event) -> None:
        """Queue an event (slip, session, tracker, service) for the store and the websocket."""
        self._queue_event(event)

    def _queue_event(self, event: TrackerEvent | Event) -> None:
        with self._cond:
            self._pending_events.append(event)
            self._cond.notify()

    def call(self, fn: Callable[[], object], timeout: float = 30.0):
        """Run `fn` on the pipeline thread after the frames handed over until now (not those after them), and
        return its result."""
        fut: Future = Future()
        with self._cond:
            # The frames handed over until now come before it, any after it (a session's frames end where
            # its raw recording was closed, not where this thread, behind, got to its stop).
            self._commands.append((fn, fut, len(self._pending)))
            self._cond.notify()
        if self._thread is None or not self._thread.is_alive():
            raise FlockcalError("the live pipeline is not running; restart the service")
        return fut.result(timeout)

    def start(self, stop_session: Callable[[LimitStop], None] | None = None,
              flush_held_rows: Callable[[], bool] | None = None, beside: Callable[[], float] | None = None) -> None:
        """Start the pipeline and fit threads. A limit reached stops its session through `stop_session`
        (SessionManager.stop_for_limit: on a thread of its own, as a client's stop); room again on the disk
        stores the session rows held meanwhile with `flush_held_rows`. `beside` (the live streams'
        `Outputs.hand_over`) runs on this thread at the start of every step, and on its own when the time it
        returned (monotonic seconds; inf: none) comes first: it must never wait."""
        self._beside = beside
        if stop_session is not None:
            self._stop_session = stop_session
        if flush_held_rows is not None:
            self._flush_held_rows = flush_held_rows
        self._thread = threading.Thread(target=self._run, name="flockcal-pipeline", daemon=True)
        self._thread.start()
        self.fitter.start()

    def stop(self) -> None:
        with self._cond:
            self._stop = True
            self._cond.notify()
        self.fitter.stop()
        if self._thread:
            self._thread.join(10)

    def _wake(self) -> None:
        """The fit worker has a result: wake the pipeline thread (called on the fit thread)."""
        with self._cond:
            self._cond.notify()

    # --- session control (run on the pipeline thread through `call`) ----------------------------------
    def begin_session(self, live: LiveSession) -> None:
        def install():
            if self.live is not None:
                raise FlockcalError(f"session {self.live.id} is still live")
            live.cal = LiveCalibration(self.names, self.rate_hz(), live.profile, hierarchy=live.hierarchy,
                                       root=live.root, skeleton=live.skeleton, performer=live.performer,
                                       detect_slips=self.detect_slips, residual_period_s=self.residual_s)
            self.live = live
            self.snapshots.residuals.clear()
            self._publish()

        self.call(install)

    def end_session(self) -> tuple[LiveSession, Calibration | None, str | None]:
        """Stop recording; returns (session, its final fit with the session's slips, or None; why there is
        no fit)."""

        def finish():
            live = self.live
            if live is None:
                raise FlockcalError("no session is live")
            cal = live.cal
            self._record(live, cal.finish())
            self.persistence.flush_db(live)
            result, error = None, None
            if cal.frames > 0:
                try:
                    last = cal.calibration
                    final = solve_fit(cal.acc, self.names, live.hierarchy, live.root, live.skeleton,
                                      live.profile.tolerance_m, sample=cal.sample.snapshot(),
                                      humanoid=last.humanoid if last is not None else None)
                    # The stored result lists the slips the session reported (its live fits list none).
                    result = replace(final, slip_events=tuple(live.slips)) if live.slips else final
                    # What the session had reached, as the stored result has it (done joints stay done).
                    self._record(live, cal.add_final_fit(final))
                except FlockcalError as exc:
                    error = str(exc)
            else:
                error = "no frames arrived during the session"
            live.framelog.close()
            self.live = None
            if result is not None:
                self.pose_fit = cal.calibration
                self.pose_fit_id = (live.id, None)
            self._publish()
            return live, result, error

        return self.call(finish)

    # --- the thread ----------------------------------------------------------------------------------
    def _run(self) -> None:
        name_os_thread("fc-pipeline")
        last_publish = 0.0
        backlog = False
        while True:
            beside_only = False
            with self._cond:
                while not self._stop and not self._commands and not backlog:
                    has_work = bool(self._pending or self._pending_events or self.fitter.has_result())
                    # Publish as soon as frames arrive, but no more than publish_hz; status twice a second.
                    due = last_publish + (self.min_publish_s if has_work else 0.5)
                    now = self.clock.monotonic()
                    if now >= due:
                        break
                    if now >= self._beside_due:  # the streams' time, nothing else's
                        beside_only = True
                        break
                    self.clock.wait(self._cond, min(due, self._beside_due) - now)
            if beside_only:
                self._run_beside()
                continue
            with self._cond:
                stopping = self._stop
                if stopping:
                    batches, self._pending = self._pending, []
                    commands, self._commands = [(fn, fut) for fn, fut, _ in self._commands], []
                elif self._commands:  # a session starts and stops at the frames received when it was asked
                    (fn, fut, cut), *rest = self._commands
                    batches, self._pending = self._pending[:cut], self._pending[cut:]
                    self._commands = [(f, u, c - len(batches)) for f, u, c in rest]
                    commands = [(fn, fut)]
                else:
                    batches, self._pending = _step_of(self._pending, MAX_STEP_S * self.rate_hz())
                    commands = []
                backlog = bool(self._pending)
                events, self._pending_events = self._pending_events, []
            self._run_beside()  # the streams first: their frames go out before this step's work on them
            try:
                if batches:
                    self._process_frames(batches)
                if events:
                    self._add_events(events)
                for fn, fut in commands:
                    try:
                        fut.set_result(fn())
                    except BaseException as exc:  # handed back to the caller
                        fut.set_exception(exc)
                self._publish()
            except Exception:  # the pipeline must survive a bad batch; the log says why
                log.exception("pipeline step failed")
            last_publish = self.clock.monotonic()
            if stopping:
                if self.live is not None:
                    self.persistence.flush_db(self.live)
                    self.live.framelog.flush()
                return

    def _run_beside(self) -> None:
        if self._beside is None:
            return
        try:
            self._beside_due = self._beside()
        except Exception:  # the streams' fault is not the pipeline's
            log.exception("work beside the pipeline failed")
            self._beside_due = math.inf

    def _session_time(self) -> float | None:
        """The live session's time of its newest frame; None without a session or before its first frame."""
        live = self.live
        return live.cal.time_s if live is not None and live.cal.t0 is not None else None

    def _storage_failed(self, why) -> None:
        """A write failed for want of room (the database, the frame log, the raw recording): the disk is
        full, and the live session stops recording (server/limits.py)."""
        if self.limits is None:
            return
        for ev in self.limits.storage_failed(str(why)):
            self.add_event(ev)
        if self.live is not None:
            self._check_limits(self.live)

    def _check_limits(self, live: LiveSession) -> None:
        """Session length, free disk (server/limits.py): a limit reached is an event, and the session stops."""
        stop = self.limits.check(live.id, live.cal.time_s)
        if stop is not None:
            self.add_event(stop.event())
            self._stop_session(stop)

    def _process_frames(self, batches: list[Frames]) -> None:
        frames = self.ingest.take(batches)
        live = self.live
        if frames is None or live is None:
            return
        live.framelog.write(frames.times, frames.rotations, frames.positions, frames.valid, frames.words)
        if live.framelog.error is not None and not live.log_failed:
            live.log_failed = True  # the log ended at its last whole record; the live fit goes on
            self._storage_failed(f"{live.framelog.path.name}: {live.framelog.error.strerror or live.framelog.error}")
        # Behind the tracker, the slip loop refits less often until it has caught up; keeping up, it runs
        # at the measured 1/30 s cadence.
        lag = self.clock.monotonic() - self.ingest.last_frame_time
        catch_up = FAR_CATCH_UP if lag > FAR_BEHIND_S else CATCH_UP if lag > BEHIND_S else 1
        update = live.cal.add_frames(frames, catch_up)
        if self.limits is not None:
            self._check_limits(live)
        self._record(live, update)

    def _record(self, live: LiveSession, update: LiveUpdate) -> None:
        """What the live calibration gave, to the store and the snapshots: becoming done or undone (before
        the slips that undid it), the slip events, a slip watch that failed, the residual samples."""
        if not update:
            return
        events = []
        if update.done is not None:
            events.append(Event.new("session", session_id=live.id, time_s=update.done.time_s,
                                    action=update.done.action, message=update.done.message))
        events += [slip_event(ev) for ev in update.events]
        live.slips += [ev for ev in update.events if ev.kind == "slip"]  # what its result lists (not swaps)
        exc = update.failure
        if exc is not None:
            log.error("slip monitor failed; slips are no longer watched in session %s", live.id,
                      exc_info=(type(exc), exc, exc.__traceback__))
            events.append(Event.new(
                "tracker", kind="slip_watch_failed",
                message=f"slip detection stopped for this session ({type(exc).__name__}: {exc}); "
                        f"recording and fitting go on; restart the session to watch for slips again"))
        if events:
            self._add_events(events)
        if update.residuals:
            self.persistence.add_residuals(live, self.snapshots.add_residuals(update.residuals))

    def _add_events(self, events: list[TrackerEvent | Event]) -> None:
        tracker = [ev for ev in events if isinstance(ev, TrackerEvent)]
        self.persistence.add_events([tracker_event(ev) if isinstance(ev, TrackerEvent) else ev for ev in events],
                                    self.live, self._session_time())
        for ev in tracker:  # the reader's raw recording ran out of room
            if ev.kind == "recording_stopped" and ev.disk_full:
                self._storage_failed(ev.message or "the raw recording")

    def _publish(self) -> None:
        live = self.live
        now = self.clock.monotonic()
        if self.limits is not None:  # the disk, once a second (full, or room again)
            for ev in self.limits.tick(lambda: self.persistence.flush_held() and self._flush_held_rows()):
                self.add_event(ev)
        if live is not None:
            self.persistence.tick(live, now)
            self._take_fit(live)
            since = now - self._last_fit_time
            if (live.cal.fit_due and since >= self.min_fit_s
                    and not self.fitter.busy  # only this thread submits, so it stays free until then
                    and (since >= BEHIND_FIT_S or not self._behind(now))):
                # Hand a copy of the Gram matrix to the fit thread; frames keep flowing meanwhile.
                job = live.cal.fit_input()
                self.fitter.submit(FitJob(live.id, job.acc, live.hierarchy, live.root, live.skeleton,
                                          (job.time_s, job.epoch), live.profile.tolerance_m, job.sample,
                                          job.previous))
                # Keep a fixed grid (not "period after the last start") so the rate holds at fit_hz.
                self._last_fit_time = max(self._last_fit_time + self.min_fit_s, now - self.min_fit_s)
        snap = self._make_snapshot()
        if self.on_publish is not None:
            self.on_publish(snap)

    def _behind(self, now: float) -> bool:
        """Frames wait while those just processed are over BEHIND_S old (reader times are monotonic)."""
        last = self.ingest.last_frame_time
        if last is None or now - last <= BEHIND_S:
            return False
        with self._cond:
            return bool(self._pending)

    def _take_fit(self, live: LiveSession) -> None:
        done = self.fitter.take()
        if done is None or done.session_id != live.id:
            return
        if done.calibration is None:
            live.fit_error = done.error
            return
        live.fit = FitView(done.calibration)
        live.fit_error = None
        self.pose_fit = done.calibration
        self._fit_seq += 1
        self.pose_fit_id = (live.id, self._fit_seq)
        self._record(live, live.cal.add_fit(done.calibration, *done.stamp))

    def _make_snapshot(self) -> Snapshot:
        live = self.live
        return self.snapshots.make(
            live=live, ingest=self.ingest, persistence=self.persistence, fit_seq=self._fit_seq,
            fits_done=self.fitter.fits_done, fit_seconds=self.fitter.fit_seconds, pose_fit=self.pose_fit,
            pose_fit_id=self.pose_fit_id)
