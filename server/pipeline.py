"""The live pipeline: frames from the reader thread → the session's accumulator → fits → snapshots.

One thread ("fc-pipeline") owns all mutable live state and runs the parts, each holding its own:
`Ingest` (newest pose, frames into the session), `ResidualSampler` and the slip loop (server/sampling.py),
`Persistence` (store, frame log), `SnapshotMaker`. `FitWorker` refits on its own thread. The reader only
appends to a queue; the event loop only reads the newest immutable Snapshot. See docs/server.md.
"""

from __future__ import annotations

import logging
import threading
import time
from concurrent.futures import Future
from typing import Callable

from flockcal.errors import FlockcalError
from flockcal.frames import Frames
from flockcal.server.fitting import SLIP_FIELDS, FitJob, FitWorker, fit_calibration, new_accumulator
from flockcal.server.ingest import Ingest
from flockcal.server.live_session import LiveSession
from flockcal.server.persistence import Persistence
from flockcal.server.sampling import ResidualSampler, watch_flush, watch_step
from flockcal.server.snapshot import Snapshot, SnapshotMaker
from flockcal.server.store import Store
from flockcal.solver.calibration import Calibration
from flockcal.solver.progress import Profile, default_target, profile
from flockcal.solver.progress_tracker import ProgressTracker
from flockcal.solver.progress_words import done_change
from flockcal.solver.slippage.watch import SlipWatch
from flockcal.threads import name_os_thread

__all__ = ["SLIP_FIELDS", "LiveSession", "Pipeline"]

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
# A fitted tree (automatic topology) must stay the fits' tree this long, in session time, before the slip
# loop watches it, the first one too: early fitted trees flicker, and a step on a wrong edge is no slip
# (early trees raised false events in the first seconds). Nothing is lost by waiting: the monitor keeps
# the joints both trees share and works new ones out from the frames it keeps (solver/slippage/watch.py).
TREE_SETTLE_S = 3.0


def _step_of(pending: list[Frames], frames: float) -> tuple[list[Frames], list[Frames]]:
    """(the first batches, at least one, holding at most `frames` frames; the rest)."""
    total, k = 0, 0
    while k < len(pending) and (k == 0 or total + len(pending[k]) <= frames):
        total += len(pending[k])
        k += 1
    return pending[:k], pending[k:]


class Pipeline:
    """Owns the live state; `feed`, `tracker_event`, `add_event` and `call` may be called from any thread.

    Threads: `_cond` guards the hand-over queue (`_pending`, `_pending_events`, `_commands`) and `_stop`,
    and nothing else; every other field, and every part but the fit worker, belongs to the pipeline
    thread (`_run`, and the functions it runs through `call`). The fit worker guards its own slots with
    its own lock; the only order ever taken is `_cond` → the fit worker's lock."""

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
        self.default_profile = "stage"  # a session that names none (`flockcal serve --profile`)
        self.m = len(self.names)
        self.store = store
        self.min_publish_s = 1.0 / publish_hz
        self.min_fit_s = 1.0 / fit_hz
        self.on_publish = on_publish
        self.limits = None  # SessionLimits (server/limits.py), set by the service: session length, free disk
        self.detect_slips = detect_slips
        self.rate_hz = rate_hz or (lambda: 144.0)
        self._cond = threading.Condition()
        self._pending: list[Frames] = []
        self._pending_events: list[dict] = []
        self._commands: list[tuple[Callable, Future]] = []
        self._stop = False
        self._thread: threading.Thread | None = None
        # The parts, and the state below, belong to the pipeline thread.
        self.ingest = Ingest(self.m)
        self.sampler = ResidualSampler(self.names, 1.0 / residual_hz)
        self.persistence = Persistence(store, on_storage_failed=self._storage_failed)
        self.fitter = FitWorker(self.names, self.tolerance, on_done=self._wake)
        self.snapshots = SnapshotMaker(self.names, source_status, self.target)
        self.live: LiveSession | None = None
        self.pose_fit: Calibration | None = None  # the fit the live skeleton is drawn with
        # Whose fit that is: (session id, fit_seq), fit_seq None for a stopped session's final (stored) fit;
        # the pose's `rig` carries it so a page knows which /gltf rig the stream drives.
        self.pose_fit_id: tuple[str, int | None] | None = None
        self.fits_done = 0
        self.fit_seconds = 0.0
        self._fit_seq = 0
        self._last_fit_time = 0.0
        self._tree_candidate: tuple[frozenset, float] | None = None  # a fitted tree waiting to settle
        self._watched: tuple | None = None  # (the slip loop's joints array, its (child, parent) set)
        self._make_snapshot()

    # --- called from other threads -----------------------------------------------------------------
    @property
    def snapshot(self) -> Snapshot:
        return self.snapshots.current

    def feed(self, frames: Frames) -> None:
        """Reader callback: hand over a batch of frames; never blocks for long."""
        with self._cond:
            self._pending.append(frames)
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

    def profile(self, name: str | None = None) -> Profile:
        """The named profile (default: the service's), the stage one with this service's tolerance and target."""
        return profile(name or self.default_profile, self.tolerance, self.target)

    # --- session control (run on the pipeline thread through `call`) ----------------------------------
    def begin_session(self, live: LiveSession) -> None:
        def install():
            if self.live is not None:
                raise FlockcalError(f"session {self.live.id} is still live")
            live.acc = new_accumulator(self.m, segmented=self.detect_slips)
            if self.detect_slips:
                # The slip loop feeds the accumulator in its micro-batches (it refits between them).
                live.watch = SlipWatch(None, self.m, self.rate_hz(), self.names, segments=live.acc, strict=False)
            # A given tree (hierarchy or saved skeleton) cannot re-link, so its joints need not wait for it to settle.
            if live.profile is None:
                live.profile = self.profile()
            live.tracker = ProgressTracker.for_profile(
                live.profile, tree_fixed=live.hierarchy is not None or live.skeleton is not None)
            self.live = live
            self._tree_candidate = None
            self.sampler.reset()
            self.sampler.recent.clear()
            self._publish()

        self.call(install)

    def end_session(self) -> tuple[LiveSession, dict | None, str | None]:
        """Stop recording; returns (session, final fit dict or None, why there is no fit)."""

        def finish():
            live = self.live
            if live is None:
                raise FlockcalError("no session is live")
            if live.watch is not None:
                self._slips(live, watch_flush(live))
            self.sampler.drain(live)
            self.sampler.flush(live)
            self.persistence.flush_db(live)
            result, error = None, None
            if live.acc.frames > 0:
                try:
                    result, live.calibration = fit_calibration(live.acc, self.names, live.hierarchy, live.root,
                                                               live.skeleton, live.profile.tolerance_m)
                    slips = self.persistence.slip_events(live, SLIP_FIELDS)
                    if slips:
                        result["slip_events"] = slips
                    # What the session had reached, as the stored result has it (done joints stay done).
                    self._progress_step(live, live.calibration, self.ingest.session_time(live), live.slip_epoch)
                except FlockcalError as exc:
                    error = str(exc)
            else:
                error = "no frames arrived during the session"
            live.framelog.close()
            self.live = None
            if result:
                self.pose_fit = live.calibration
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
            with self._cond:
                while not self._stop and not self._commands and not backlog:
                    has_work = bool(self._pending or self._pending_events or self.fitter.has_result())
                    # Publish as soon as frames arrive, but no more than publish_hz; status twice a second.
                    due = last_publish + (self.min_publish_s if has_work else 0.5)
                    now = time.monotonic()
                    if now >= due:
                        break
                    self._cond.wait(due - now)
                stopping = self._stop
                if stopping or self._commands:  # a session starts and stops after every frame received
                    batches, self._pending = self._pending, []
                else:
                    batches, self._pending = _step_of(self._pending, MAX_STEP_S * self.rate_hz())
                backlog = bool(self._pending)
                events, self._pending_events = self._pending_events, []
                commands, self._commands = self._commands, []
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
            last_publish = time.monotonic()
            if stopping:
                if self.live is not None:
                    self.persistence.flush_db(self.live)
                    self.live.framelog.flush()
                return

    def _storage_failed(self, why) -> None:
        """A write failed for want of room (the database, the frame log, the raw recording): the disk is
        full, and the live session stops recording (server/limits.py)."""
        if self.limits is None:
            return
        live = self.live
        self.limits.storage_failed(str(why), live.id if live is not None else None,
                                   self.ingest.session_time(live) if live is not None else None)

    def _process_frames(self, batches: list[Frames]) -> None:
        live = self.live
        frames = self.ingest.take(batches, live)
        if frames is None:
            return
        if live.framelog.error is not None and not live.log_failed:
            live.log_failed = True  # the log ended at its last whole record; the live fit goes on
            self._storage_failed(f"{live.framelog.path.name}: {live.framelog.error.strerror or live.framelog.error}")
        if self.limits is not None:  # session length, free disk (server/limits.py)
            self.limits.check(live.id, float(frames[0][-1]))
        if live.watch is not None:
            # Behind the tracker, the slip loop refits less often until it has caught up; keeping up,
            # it runs at the measured 1/30 s cadence.
            lag = time.monotonic() - self.ingest.last_frame_time
            catch_up = FAR_CATCH_UP if lag > FAR_BEHIND_S else CATCH_UP if lag > BEHIND_S else 1
            self._slips(live, watch_step(live, *frames, catch_up))
        self.sampler.add(live, *frames)

    def _slips(self, live: LiveSession, events: list[dict]) -> None:
        """Events of the slip loop (it has opened the slipped sensors' segments): the epoch moves on and
        the progress hears of them before they are stored."""
        if not events:
            return
        slips = [d for d in events if d["type"] != "tracker"]
        if slips:
            live.slip_epoch += 1  # fits begun from here on see the new segments
            was_done = live.progress is not None and live.progress.done
            for d in slips:
                live.tracker.slip(d, live.slip_epoch)
            if live.calibration is not None:
                self._progress_step(live, live.calibration, self.ingest.session_time(live), live.slip_epoch - 1,
                                    was_done)
        self._add_events(events)

    def _add_events(self, events: list[dict]) -> None:
        live = self.live
        time_s = self.ingest.session_time(live) if live is not None and live.t0 is not None else None
        self.persistence.add_events(events, live, time_s)
        for ev in events:  # the reader's raw recording ran out of room
            if ev.get("kind") == "recording_stopped" and (ev.get("data") or {}).get("disk_full"):
                self._storage_failed(ev.get("message") or "the raw recording")

    def _publish(self) -> None:
        live = self.live
        now = time.monotonic()
        if self.limits is not None:
            self.limits.tick()  # the disk, once a second (full, or room again)
        if live is not None:
            self.persistence.tick(live, now)
            self._take_fit(live)
            since = now - self._last_fit_time
            if (live.acc.frames > live.fit_frames and since >= self.min_fit_s
                    and not self.fitter.busy  # only this thread submits, so it stays free until then
                    and (since >= BEHIND_FIT_S or not self._behind(now))):
                # Hand a copy of the Gram matrix to the fit thread; frames keep flowing meanwhile.
                self.fitter.submit(FitJob(live.id, live.acc.copy(), live.hierarchy, live.root, live.skeleton,
                                          (self.ingest.session_time(live), live.slip_epoch), live.profile.tolerance_m))
                # Keep a fixed grid (not "period after the last start") so the rate holds at fit_hz.
                self._last_fit_time = max(self._last_fit_time + self.min_fit_s, now - self.min_fit_s)
                live.fit_frames = live.acc.frames
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
        if done is None:
            return
        self.fits_done += 1
        self.fit_seconds += done.seconds
        if done.session_id != live.id:
            return
        if done.fit is None:
            live.fit_error = done.error
            return
        live.fit, live.calibration = done.fit, done.calibration
        live.fit_error = None
        self.pose_fit = done.calibration
        self._fit_seq += 1
        self.pose_fit_id = (live.id, self._fit_seq)
        time_s, epoch = done.stamp
        if live.watch is not None and len(done.calibration.joints):
            self._watch_tree(live, self.sampler.joints(done.calibration).pairs, time_s)
        self._progress_step(live, done.calibration, time_s, epoch)

    def _watch_tree(self, live: LiveSession, pairs, time_s: float) -> None:
        """Hand the fit's tree to the slip loop: at once for a given tree, else once it has stayed the
        fits' tree for TREE_SETTLE_S (a tree that flickers back is never handed on)."""
        key = frozenset(map(tuple, pairs.tolist()))
        watched = live.watch.joints
        if watched is not None and (self._watched is None or self._watched[0] is not watched):
            self._watched = (watched, frozenset(map(tuple, watched.tolist())))
        if watched is not None and key == self._watched[1]:
            # The tree watched already (nearly every refit): `watch` would find no change, at the cost of
            # comparing the two lists in numpy 30 times a second.
            self._tree_candidate = None
            return
        if live.hierarchy is not None or live.skeleton is not None:
            self._tree_candidate = None
            live.watch.watch(pairs)
            return
        if self._tree_candidate is None or self._tree_candidate[0] != key:
            self._tree_candidate = (key, time_s)
        elif time_s - self._tree_candidate[1] >= TREE_SETTLE_S:
            self._tree_candidate = None
            live.watch.watch(pairs)

    def _progress_step(self, live: LiveSession, fit: Calibration, time_s: float, epoch: int,
                       was_done: bool | None = None) -> None:
        """Fold a fit into the session's progress; becoming done (or undone) is an event of its own."""
        if was_done is None:
            was_done = live.progress is not None and live.progress.done
        try:
            live.progress = live.tracker.add_fit(fit, time_s, epoch)
        except (KeyError, TypeError, ValueError) as exc:  # a malformed fit must not stop the pipeline
            log.warning("progress not updated: %s", exc)
            return
        change = done_change(live.progress, was_done, live.performer, live.profile, time_s)
        if change is not None:
            action, message = change
            self._add_events([{"type": "session", "session_id": live.id, "action": action, "time_s": time_s,
                               "message": message}])

    def _make_snapshot(self) -> Snapshot:
        live = self.live
        return self.snapshots.make(
            live=live, session_time=self.ingest.session_time(live) if live is not None else 0.0,
            ingest=self.ingest, sampler=self.sampler, persistence=self.persistence, fit_seq=self._fit_seq,
            fits_done=self.fits_done, fit_seconds=self.fit_seconds, pose_fit=self.pose_fit,
            pose_fit_id=self.pose_fit_id)
