"""Sessions: one performer's calibration take — start, live results, stop, store, re-solve.

The manager is the only writer of session rows. At most one session is live (one tracker per
service); its live results come from the pipeline's snapshots, a stopped one's from the store.
"""

from __future__ import annotations

import logging
import secrets
import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable

from flockcal.errors import FlockcalError
from flockcal.server.clock import ServiceClock
from flockcal.server.errors import BadRequest, Conflict, InsufficientStorage, NotFound, Unavailable
from flockcal.server.framelog import FrameLog, read_frames
from flockcal.server.events import Event
from flockcal.server.fitting import FitView
from flockcal.server.holds import RETRY_AFTER_S, FileHolds
from flockcal.server.lease import SessionLeases
from flockcal.server.limits import LimitStop
from flockcal.server.live_session import LiveSession
from flockcal.server.pipeline import Pipeline
from flockcal.server.retention import Policy, Retention
from flockcal.server.settings import PERFORMER_RE, PERFORMER_RULE
from flockcal.server.store import SessionRow, Store
from flockcal.solver.calibration import Calibration
from flockcal.solver.hierarchy import check_hierarchy
from flockcal.solver.progress import Profile, Progress, progress_of, waiting

log = logging.getLogger(__name__)

FRAMES_SUFFIX = ".frames"
RAW_SUFFIX = ".fobraw"
SKELETON_SUFFIX = ".skeleton.json"  # the saved skeleton a session was started with (for stop and resolve)


def new_session_id(stamp: float | None = None) -> str:
    return time.strftime("%Y%m%d-%H%M%S", time.localtime(stamp)) + "-" + secrets.token_hex(3)


@dataclass(frozen=True)
class SessionEnd:
    """What a stop writes to the session's row (`SessionManager.update_row`): held in memory, as it is, while
    the database cannot take it."""

    state: str
    stopped_at: float
    duration_s: float
    frames: int
    result: Calibration | None  # the final fit, with the session's slips
    note: str | None
    progress: Progress | None

    def columns(self) -> dict:
        """The row's columns it sets (Store.update_session)."""
        return dict(state=self.state, stopped_at=self.stopped_at, duration_s=self.duration_s, frames=self.frames,
                    result=self.result, note=self.note, progress=self.progress)


@dataclass(frozen=True)
class SessionProgress:
    """A session's progress with where it comes from (GET /api/sessions/{id}/progress): the live one as the
    service keeps it, a stopped one as it stood at its stop (or its re-solve)."""

    session_id: str
    live: bool
    time_s: float | None
    fit_seq: int | None
    frames: int
    progress: Progress

    def to_dict(self) -> dict:
        return {"session_id": self.session_id, "live": self.live, "time_s": self.time_s, "fit_seq": self.fit_seq,
                "frames": self.frames, **self.progress.to_dict()}


class SessionManager:
    """Starts, stops and reads sessions, recorded under `data_dir`/recordings. `profiles(name)` gives a
    session's Profile (Settings.session_profile); `raw_recorder` is the frame source
    (start_recording(path)/stop_recording()) for the .fobraw, or None. Its leases (server/lease.py: sessions
    that end when their client stops renewing) and its retention (server/retention.py: pins, pruned files
    answer 410, the pruner woken after a stop) are its own parts, built on it."""

    def __init__(self, store: Store, pipeline: Pipeline, data_dir: Path, device: str,
                 rate_hz: float | None | Callable[[], float | None], profiles: Callable[[str | None], Profile],
                 raw_recorder=None, retention_policy: Policy | None = None, retention_interval_s: float = 60.0,
                 clock: ServiceClock | None = None):
        self.store = store
        # Stamps (created_at), measured durations and lease deadlines: one clock (server/clock.py).
        self.clock = clock if clock is not None else pipeline.clock
        self.pipeline = pipeline
        self.recordings = Path(data_dir) / "recordings"
        self.recordings.mkdir(parents=True, exist_ok=True)
        self.device = device
        self.rate_hz = rate_hz
        self.profiles = profiles
        self.raw_recorder = raw_recorder
        self.holds = FileHolds()  # downloads in progress hold a session's files (server/holds.py)
        self.leases = SessionLeases(stop=self.stop, add_event=pipeline.add_event, clock=self.clock)
        self.retention = Retention(store, self, Path(data_dir), retention_policy or Policy(), pipeline.add_event,
                                   interval_s=retention_interval_s, clock=self.clock)
        self._lock = threading.Lock()  # one start/stop at a time
        # Row updates the database could not take (a full disk): shown from memory, stored once it can.
        self._held_rows: dict[str, SessionEnd] = {}
        self._held_lock = threading.Lock()

    @property
    def names(self) -> tuple[str, ...]:
        return self.pipeline.names

    def stop_for_limit(self, limit: LimitStop) -> None:
        """Stop a session that reached a limit (server/limits.py) on a thread of its own, as a client's stop
        would, and note why on its row (pipeline thread: the stop itself waits for that thread)."""

        def stop():
            try:
                self.stop(limit.session_id, note=limit.message)
            except Exception as exc:  # stopped meanwhile by a client: nothing left to do
                log.info("limit stop of %s: %s", limit.session_id, exc)

        threading.Thread(target=stop, name="fc-limit-stop", daemon=True).start()

    def frames_path(self, session_id: str) -> Path:
        return self.recordings / f"{session_id}{FRAMES_SUFFIX}"

    def raw_path(self, session_id: str) -> Path:
        return self.recordings / f"{session_id}{RAW_SUFFIX}"

    def skeleton_path(self, session_id: str) -> Path:
        return self.recordings / f"{session_id}{SKELETON_SUFFIX}"

    def session_skeleton(self, session_id: str):
        """The Skeleton the session was started with, or None for a free fit."""
        import json

        from flockcal.exports.skeleton import parse_skeleton

        path = self.skeleton_path(session_id)
        if not path.exists():
            return None
        return parse_skeleton(json.loads(path.read_text()), origin=path.name)

    def live_id(self) -> str | None:
        s = self.pipeline.snapshot.session
        return s.id if s else None

    # --- checks ------------------------------------------------------------------------------------
    def check_hierarchy(self, hierarchy: dict | None, root: str | None) -> None:
        """BadRequest, with the solver's message, unless `root` is a sensor and `hierarchy` one tree over
        the sensors rooted there (solver/hierarchy.py: the one check, which the fit makes again)."""
        check_hierarchy(hierarchy, self.names, root, error=BadRequest)

    # --- lifecycle ---------------------------------------------------------------------------------
    def start(self, performer: str, hierarchy: dict | None = None, root: str | None = None,
              skeleton=None, skeleton_name: str | None = None, profile: str | None = None,
              lease_s: float | None = None) -> SessionRow:
        """Start a session; with a saved `skeleton` (flockcal.exports.skeleton.Skeleton) its tree and
        bones are kept and only the sensor placements are fitted. `profile` ("stage" or "kiosk", default
        the service's) says how it decides it is calibrated (solver/progress.py). With `lease_s` the session
        ends that long after its client last renewed it (server/lease.py)."""
        try:
            prof = self.profiles(profile)
        except ValueError as exc:
            raise BadRequest(str(exc)) from None
        if not PERFORMER_RE.fullmatch(performer) or not performer.strip():
            raise BadRequest(f"performer name must be {PERFORMER_RULE}")
        if skeleton is not None:
            if root is not None and root != skeleton.root:
                raise BadRequest(f"skeleton {skeleton_name!r} is rooted at {skeleton.root!r}; leave 'root' out")
            hierarchy, root = skeleton.hierarchy, skeleton.root
        self.check_hierarchy(hierarchy, root)
        with self._lock:
            live = self.live_id()
            if live is not None:
                raise Conflict(f"session {live} is live; stop it (POST /api/sessions/{live}/stop) before starting another")
            now = self.clock.read()
            sid = new_session_id(now.stamp)
            rate = self.rate_hz() if callable(self.rate_hz) else self.rate_hz
            rate = float(rate) if rate else None  # None: not known (a take then uses its arrivals' mean rate)
            row = {
                "id": sid, "performer": performer, "state": "live", "root": root, "hierarchy": hierarchy,
                "names": list(self.names), "device": self.device, "rate_hz": rate,
                "created_at": now.stamp, "frames": 0, "recording": self.frames_path(sid).name,
                "profile": prof.name,
            }
            try:
                framelog = FrameLog(self.frames_path(sid), list(self.names), rate, clock=self.clock)
            except OSError as exc:
                raise InsufficientStorage(f"cannot create the session's recording {self.frames_path(sid)}: "
                                          f"{exc.strerror}; make room on that disk (DELETE old sessions)") from None
            try:
                if skeleton is not None:
                    import json

                    self.skeleton_path(sid).write_text(json.dumps(dict(skeleton.data, preset=skeleton_name)))
                self.store.insert_session(row)
                try:
                    self.retention.recorded(sid, now)
                except BaseException:
                    self.store.delete_session(sid)
                    raise
            except BaseException as exc:  # a full disk: nothing of the session is left behind
                framelog.close()
                self.frames_path(sid).unlink(missing_ok=True)
                self.skeleton_path(sid).unlink(missing_ok=True)
                if isinstance(exc, OSError):
                    raise InsufficientStorage(f"cannot start a session: {exc.strerror} ({exc.filename}); make room "
                                              "on that disk (DELETE old sessions)") from None
                raise
            if self.raw_recorder is not None:
                try:
                    self.raw_recorder.start_recording(self.raw_path(sid))
                except FlockcalError as exc:
                    log.warning("raw recording unavailable: %s", exc)
            session = LiveSession(sid, performer, self.names, hierarchy, root, framelog, prof, skeleton=skeleton,
                                  started_wall=now.stamp, started_mono=now.mono)
            try:
                self.pipeline.begin_session(session)
            except BaseException:
                framelog.close()
                self.store.delete_session(sid)
                self.retention.forget(sid)
                self.skeleton_path(sid).unlink(missing_ok=True)
                raise
            if lease_s is not None:
                self.leases.grant(sid, lease_s)
            self.pipeline.add_event(Event.new("session", session_id=sid, time_s=0.0, action="started",
                                              message=f"session {sid} started for {performer}"))
            return self.get(sid)

    def renew(self, session_id: str) -> dict:
        """Renew a live session's lease (POST /api/sessions/{id}/lease)."""
        row = self._row(session_id)
        if row.state != "live" or self.live_id() != session_id:
            raise Conflict(f"session {session_id} is not live (it is {row.state}); there is no lease to renew")
        lease = self.leases.renew(session_id)
        if lease is None:
            raise Conflict(f"session {session_id} was started without a lease (POST /api/sessions with lease_s)")
        return {"session_id": session_id, "lease_s": lease, "expires_in_s": round(self.leases.remaining(session_id), 3)}

    def stop(self, session_id: str, note: str | None = None) -> SessionRow:
        """Stop the live session; `note` says why when the service stopped it (a limit, a lapsed lease). It
        lands in the same row update as the stopped state, so no reader sees one without the other."""
        with self._lock:
            row = self._row(session_id)
            if row.state != "live" or self.live_id() != session_id:
                raise Conflict(f"session {session_id} is not live (it is {row.state}); nothing to stop")
            self.leases.release(session_id)
            if self.raw_recorder is not None:
                try:
                    self.raw_recorder.stop_recording()
                except FlockcalError as exc:
                    log.warning("raw recording did not close cleanly: %s", exc)
            live, result, error = self.pipeline.end_session()
            notes = [note] if note else []
            if live.framelog.error is not None:
                notes.append(f"recording stopped early ({live.framelog.error.strerror or live.framelog.error}): "
                             f"{live.framelog.path.name} holds the frames written until then")
            if result is None:
                notes.append(f"no result: {error}")
            note = "; ".join(notes) or None
            # Measured on the monotonic clock; stopped_at follows from it, so a step of the wall clock during
            # the session (an event of its own) can neither stretch it nor put its end before its start.
            duration = max(self.clock.monotonic() - live.started_mono, 0.0)
            self.update_row(session_id, SessionEnd("stopped", row.created_at + duration, round(duration, 3), live.frames,
                                                   result, note, live.cal.progress if result is not None else None))
            self.pipeline.add_event(Event.new("session", session_id=session_id, time_s=None, action="stopped",
                                              message=f"session {session_id} stopped after {live.frames} frames"))
            self.retention.wake()
            return self.get(session_id)

    def delete(self, session_id: str) -> None:
        with self._lock:
            row = self._row(session_id)
            if row.state == "live" and self.live_id() == session_id:
                raise Conflict(f"session {session_id} is live; stop it before deleting it")
            downloads = self.holds.claim(session_id, lambda: NotFound(f"session {session_id} was deleted"))
            if downloads:
                exc = Conflict(f"session {session_id} is being downloaded ({downloads} download"
                               f"{'s' if downloads > 1 else ''} in progress, each sent whole); DELETE it again once "
                               f"{'they have' if downloads > 1 else 'it has'} finished")
                exc.retry_after = RETRY_AFTER_S
                raise exc
            try:
                self._delete(session_id)
            finally:
                self.holds.unclaim(session_id)

    def _delete(self, session_id: str) -> None:
        """Remove the session's rows and files (under the lock, its files claimed from downloads)."""
        files = (self.frames_path(session_id), self.raw_path(session_id), self.skeleton_path(session_id))
        try:
            self.store.delete_session(session_id)
        except InsufficientStorage:
            # The database needs room to delete rows too: the session's files are what makes it.
            for p in files:
                p.unlink(missing_ok=True)
            try:
                self.store.delete_session(session_id)
            except InsufficientStorage as exc:
                raise InsufficientStorage(f"session {session_id}'s recordings were removed, but its rows could "
                                          f"not be: {exc}; DELETE it again once there is room") from None
        for p in files:
            p.unlink(missing_ok=True)
        with self._held_lock:
            self._held_rows.pop(session_id, None)
        self.retention.forget(session_id)

    # --- rows the database could not take ------------------------------------------------------------
    def update_row(self, session_id: str, end: SessionEnd) -> None:
        """Write a stop to the session's row; on a full disk it is held in memory (readers see it) and
        stored by `flush_held_rows` once the database can take it."""
        with self._held_lock:
            self._held_rows.pop(session_id, None)
            try:
                self.store.update_session(session_id, **end.columns())
            except (InsufficientStorage, Unavailable) as exc:
                self._held_rows[session_id] = end
                log.warning("session %s's row is held in memory: %s", session_id, exc)

    def flush_held_rows(self) -> bool:
        """Store the held row updates; True when none are left."""
        with self._held_lock:
            for sid, end in list(self._held_rows.items()):
                try:
                    self.store.update_session(sid, **end.columns())
                except (InsufficientStorage, Unavailable):
                    return False
                del self._held_rows[sid]
            return True

    def _held(self, session_id: str) -> SessionEnd | None:
        with self._held_lock:
            return self._held_rows.get(session_id)

    def _overlay(self, row: SessionRow) -> SessionRow:
        """A stored row as it is meant to be: with any stop the database has not taken yet."""
        end = self._held(row.id)
        if end is None:
            return row
        row = replace(row, state=end.state, stopped_at=end.stopped_at, duration_s=end.duration_s, frames=end.frames,
                      note=end.note, has_result=end.result is not None)
        if end.progress is not None:
            row = replace(row, progress=end.progress.progress, done=end.progress.done)
        return row

    def resolve(self, session_id: str) -> SessionRow:
        """Re-fit a stopped or interrupted session from its frame log (same hierarchy and root)."""
        with self._lock:
            row = self._row(session_id)
            if row.state == "live":
                raise Conflict(f"session {session_id} is live; stop it first")
            path = self.frames_path(session_id)
            if not path.exists():
                self._check_pruned(session_id, "recording (frames), which a re-solve needs,")
                raise NotFound(f"session {session_id} has no recording on disk ({path.name}); it cannot be re-solved")
            take = self.take(session_id)
            n = take.n_frames
            slips = self.store.slips(session_id, take.names)
            try:
                skeleton = self.session_skeleton(session_id)
                from flockcal.solver.humanoid import take_sample
                from flockcal.solver.solve import solve_take

                prof = self._profile(row)
                cal = solve_take(take, slips, row.hierarchy, row.root, skeleton, tolerance=prof.tolerance_m,
                                 sample=take_sample(take).snapshot())
            except (FlockcalError, ValueError, ArithmeticError) as exc:  # LinAlgError is a ValueError
                raise Conflict(f"session {session_id} could not be solved from its recording: {exc}") from None
            state = "stopped" if row.state == "interrupted" else row.state
            # A re-solve is one fit of the whole recording: its progress has no session history to keep.
            progress = progress_of(cal, prof.target_m, prof.tolerance_m)
            self.store.update_session(session_id, result=replace(cal, slip_events=slips), frames=n, state=state,
                                      progress=progress, note=f"re-solved from its recording ({n} frames)")
            return self.get(session_id)

    # --- reading -----------------------------------------------------------------------------------
    def _row(self, session_id: str) -> SessionRow:
        row = self.store.session(session_id)
        if row is None:
            raise NotFound(f"no session {session_id!r}; GET /api/sessions lists them")
        return self._overlay(row)

    def get(self, session_id: str) -> SessionRow:
        (row,) = self._shown([self._row(session_id)])
        return row

    def list(self) -> list[SessionRow]:
        return self._shown([self._overlay(r) for r in self.store.sessions()])

    def _shown(self, rows: list[SessionRow]) -> list[SessionRow]:
        """Rows as the API shows them: the live session's figures as they stand, its lease, the files on
        disk, the saved skeleton it was started with, retention's pin and prune."""
        snap = self.pipeline.snapshot
        out = []
        for row in rows:
            if snap.session and snap.session.id == row.id:
                row = replace(row, frames=snap.session.frames, has_result=snap.has_fit, progress=snap.session.progress,
                              done=snap.session.done, duration_s=self._live_duration(row.id))
            out.append(replace(row, has_recording=self.frames_path(row.id).exists(),
                               has_raw_recording=self.raw_path(row.id).exists(), skeleton=self._skeleton_name(row.id),
                               lease_s=self.leases.lease_s(row.id) if row.state == "live" else None))
        return self.retention.annotate(out)

    def _live_duration(self, session_id: str) -> float | None:
        """How long the live session has recorded so far, on the monotonic clock."""
        live = self.pipeline.live
        if live is None or live.id != session_id:
            return None
        return round(max(self.clock.monotonic() - live.started_mono, 0.0), 3)

    def _profile(self, row: SessionRow):
        """The profile a stored session was recorded under (sessions from before profiles: stage)."""
        try:
            return self.profiles(row.profile or "stage")
        except ValueError:
            return self.profiles("stage")

    def _check_pruned(self, session_id: str, what: str) -> None:
        self.retention.check_files(session_id, what)

    def _skeleton_name(self, session_id: str) -> str | None:
        if not self.skeleton_path(session_id).exists():
            return None
        import json

        try:  # the name only: no need to validate the whole file for a listing
            return json.loads(self.skeleton_path(session_id).read_text()).get("preset") or "?"
        except (ValueError, OSError):
            return "?"

    def result(self, session_id: str) -> tuple[FitView, bool]:
        """(the fit, live?) — the live fit for the live session, the stored one otherwise."""
        result, fit_seq = self.result_seq(session_id)
        return result, fit_seq is not None

    def result_seq(self, session_id: str) -> tuple[FitView, int | None]:
        """(the fit, fit_seq): the live session's fit with its number (read from one snapshot, so the two
        agree), or the stored result with None — the pair a pose's `rig` names (server/pose.py). The fit is
        typed (`FitView.calibration`) and made JSON once, at the route that sends it (`FitView.doc`)."""
        row = self._row(session_id)
        snap = self.pipeline.snapshot
        if snap.session and snap.session.id == session_id:
            if not snap.has_fit:
                why = snap.session.fit_error or "not enough frames yet"
                raise Conflict(f"session {session_id} has no fit yet ({why}); keep the performer moving")
            # The slips reported so far, as the stored result lists them at the stop: the live fit is made
            # ~30 times a second and carries only its joints; the events are the session's.
            slips = self.store.slips(session_id, row.names)
            if not slips:
                return snap.fit_view, snap.fit_seq
            return FitView(replace(snap.fit_view.calibration, slip_events=slips)), snap.fit_seq
        end = self._held(session_id)
        result = end.result if end is not None and end.result is not None else self.store.result(session_id)
        if result is None:
            hint = " — POST /api/sessions/{0}/resolve re-solves it from its recording".format(session_id) \
                if row.state == "interrupted" else ""
            raise Conflict(f"session {session_id} has no result ({row.note or row.state}){hint}")
        return FitView(result), None

    def progress(self, session_id: str) -> SessionProgress:
        """The session's progress (solver/progress.py) with where it comes from: the live one as the service
        keeps it, a stopped one as it stood at its stop (or its re-solve)."""
        row = self._row(session_id)
        snap = self.pipeline.snapshot
        if snap.session and snap.session.id == session_id and snap.progress is not None:
            return SessionProgress(session_id, True, snap.session.time_s, snap.fit_seq if snap.has_fit else None,
                                   snap.session.frames, snap.progress)
        end = self._held(session_id)
        progress = end.progress if end is not None and end.progress is not None else self.store.progress(session_id)
        if progress is None:
            result = self.store.result(session_id)
            if result is None:
                why = row.note or (f"the session is {row.state} and has no result")
                progress = waiting(row.names, self._profile(row).target_m, why)
            else:
                # Stopped before sessions kept their progress: its stored result, on its own.
                prof = self._profile(row)
                progress = progress_of(result, prof.target_m, prof.tolerance_m)
        return SessionProgress(session_id, False, None, None, row.frames, progress)

    def residuals(self, session_id: str, joint: str | None, since: float | None,
                  limit: int = 100_000) -> tuple[list[tuple[float, dict]], bool]:
        """(up to `limit` samples after `since`, oldest first; whether later ones exist)."""
        self._row(session_id)
        if joint is not None and joint not in self.names:
            raise BadRequest(f"joint {joint!r} is not a sensor name (a joint is named by its child body); the sensors are: {', '.join(self.names)}")
        since = float("-inf") if since is None else since
        rows = self.store.residuals(session_id, since, limit + 1)
        more = len(rows) > limit
        rows = rows[:limit]
        snap = self.pipeline.snapshot
        if snap.session and snap.session.id == session_id and not more:
            # Samples not yet flushed to the store (at most a second's worth) come from the snapshot.
            last = rows[-1][0] if rows else since
            fresh = [(s.time_s, s.rms_mm) for s in snap.residuals if s.time_s > last]
            more = len(rows) + len(fresh) > limit
            rows += fresh[:limit - len(rows)]
        if joint is not None:
            rows = [(t, {joint: v[joint]}) for t, v in rows if joint in v]
        return rows, more

    def take(self, session_id: str):
        """The session's recorded frames as a flockcal.takes.Take (times from the session start)."""
        from flockcal.takes import make_take

        self._row(session_id)
        path = self.frames_path(session_id)
        if not path.exists():
            self._check_pruned(session_id, "recording (frames)")
            raise NotFound(f"session {session_id} has no recording on disk")
        try:
            header, frames = read_frames(path)  # damaged records come back as frames with no valid sensor
        except (ValueError, OSError) as exc:
            raise Conflict(f"session {session_id}'s recording {path.name} cannot be read ({exc}); its result "
                           "and events are unaffected") from None
        n = len(frames)
        if n == 0:
            raise Conflict(f"session {session_id}'s recording holds no frames yet")
        times = frames.times - frames.times[0]
        rate = header.rate_hz or (float((n - 1) / times[-1]) if n > 1 and times[-1] > 0 else 1.0)
        # Arrival times can repeat (several records read at once); a take only needs them not to go back.
        return make_take(frames.rotations, frames.positions, list(header.names), rate, valid=frames.valid,
                         times=times, source=f"session {session_id}")

    def events(self, session_id: str, since_id: int = 0, limit: int = 1000) -> list[Event]:
        self._row(session_id)
        return self.store.events(session_id, since_id, limit)
