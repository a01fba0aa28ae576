"""Retention: how long sessions keep their bulky files (frames, raw tracker bytes) and the background
pruner that enforces `serve --keep-days` / `--keep-disk`. Results, events, the session's skeleton file and
its residual series (thinned to 1 Hz) stay; a pinned session is never pruned, nor any while one is live.
Ages are service time (server/clock.py): a step of the wall clock makes no recording older.
"""

from __future__ import annotations

import logging
import math
import os
import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import NamedTuple

from flockcal.server.clock import Reading, ServiceClock
from flockcal.server.errors import Conflict, Gone, ServerError
from flockcal.server.events import Event
from flockcal.malloc import release_free_heap

log = logging.getLogger(__name__)

# Its own table, so the sessions table (and everyone's queries of it) is untouched: a session with no
# row here is neither pinned nor pruned.
SCHEMA = """CREATE TABLE IF NOT EXISTS retention (
    session_id TEXT PRIMARY KEY,
    pinned INTEGER NOT NULL DEFAULT 0,
    pruned_at REAL,                 -- unix seconds; NULL while the frames and raw recording are on disk
    freed_bytes INTEGER,
    reason TEXT,                    -- why it was pruned (age or budget), in words
    clock_offset REAL               -- created_at less the service time it was recorded at (NULL: from before)
)"""

# The calibrated skeleton is written next to the recordings before the frames go, so /skeleton still
# answers after pruning (it is built from the result and the take's frame count and rate).
KEPT_SKELETON_SUFFIX = ".result-skeleton.json"

# Room kept under --keep-disk for the session that records next (see Retention.next_session_bytes).
ROOM_SESSIONS = 5
ROOM_SHARE = 0.25
# A pruned session keeps one residual sample per this many seconds of its time.
PRUNED_RESIDUAL_S = 1.0

GB = 1e9  # --keep-disk is in decimal gigabytes, as disks are sold and `df -H` shows them
DAY_S = 86400.0


@dataclass(frozen=True)
class Policy:
    """What to keep: the last `keep_days` days of recordings and/or a data directory under `keep_bytes`.
    Neither set: keep everything (the disk fills in the end)."""

    keep_days: float | None = None
    keep_bytes: int | None = None

    @property
    def active(self) -> bool:
        return self.keep_days is not None or self.keep_bytes is not None

    def describe(self) -> str:
        if not self.active:
            return "keep every recording (no --keep-days or --keep-disk)"
        parts = []
        if self.keep_days is not None:
            parts.append(f"the last {self.keep_days:g} days")
        if self.keep_bytes is not None:
            parts.append(f"under {self.keep_bytes / GB:g} GB")
        return "keep recordings of " + " and ".join(parts) + "; results, skeletons and events kept for good"


class PruneState(NamedTuple):
    """A session's standing with retention: pinned, and when (and why) its files were pruned, if they were."""

    pinned: bool = False
    pruned_at: float | None = None
    pruned_reason: str | None = None


class Candidate(NamedTuple):
    """A session whose files may go: its id and the service time it was recorded at."""

    id: str
    recorded_s: float


def tree_bytes(path: Path) -> int:
    """Bytes of every file under `path` (what the data directory takes on disk, give or take blocks)."""
    total = 0
    stack = [Path(path)]
    while stack:
        try:
            with os.scandir(stack.pop()) as it:
                for entry in it:
                    try:
                        if entry.is_dir(follow_symlinks=False):
                            stack.append(Path(entry.path))
                        elif entry.is_file(follow_symlinks=False):
                            total += entry.stat(follow_symlinks=False).st_size
                    except FileNotFoundError:  # removed while we looked
                        pass
        except FileNotFoundError:
            pass
    return total


class _Downloading(Exception):
    """The session's files are held by a download in progress (server/holds.py)."""


class Retention:
    """The pruner of one service. `wake()` after a session stops; it also looks every `interval_s`.

    A session is pruned whole (its .frames and .fobraw both go), oldest first: those older than
    keep_days, then more until the data directory is under the budget. Each prune is an event.
    """

    def __init__(self, store, sessions, data_dir: Path, policy: Policy, add_event, interval_s: float = 60.0, *,
                 clock: ServiceClock):
        self.store = store
        self.sessions = sessions
        self.data_dir = Path(data_dir)
        self.policy = policy
        self.add_event = add_event
        self.interval_s = float(interval_s)
        self.clock = clock
        self.store.query(SCHEMA)
        if "clock_offset" not in {n for (n,) in self.store.query("SELECT name FROM pragma_table_info('retention')")}:
            self.store.query("ALTER TABLE retention ADD COLUMN clock_offset REAL")  # databases from before
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._run_lock = threading.Lock()  # one pass at a time (the thread, or a test calling prune_once)
        self.last_run_at: float | None = None
        self.last_error: str | None = None
        self.over_budget = False  # live, pinned and kept files alone exceed the budget
        self._usage: tuple[float, int] | None = None  # (monotonic time, bytes) of the last data-directory walk
        self.heap_trims = 0
        self.heap_trim_s = 0.0  # the time they took, all told (service clock)
        self.heap_trim_max_s = 0.0

    # --- the background thread ----------------------------------------------------------------
    def start(self) -> None:
        # Runs with no policy too: the same gap between guests hands freed heap back (flockcal/malloc.py).
        if self._thread is not None:
            return
        self._thread = threading.Thread(target=self._loop, name="fc-housekeeping", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(10)

    def wake(self) -> None:
        """A session just stopped: the gap before the next one is the moment to prune."""
        self._wake.set()

    def _loop(self) -> None:
        while not self._stop.is_set():
            try:
                self._save_clock()
                self.prune_once()
                self.last_error = None
                self.trim_heap()
            except Exception as exc:  # a failing pass must not end the service; the next one retries
                self.last_error = f"{type(exc).__name__}: {exc}"
                log.exception("retention pass failed")
            self.clock.wait(self._wake, self.interval_s)
            self._wake.clear()

    def trim_heap(self) -> bool:
        """Hand freed heap back to the system in the gap between sessions (each pass while none is live, and
        at once after a stop); True if it trimmed. Not while one records: measured on a live session under
        load, trims every 30 s did not flatten its RSS steps (the arenas' pages are reused, not idle) and took
        up to 78 ms with arena locks held (docs/service.md, "A long session's memory and disk")."""
        if self.sessions.live_id() is not None:
            return False
        now = self.clock.monotonic()
        if not release_free_heap():
            return False
        took = self.clock.monotonic() - now
        self.heap_trims += 1
        self.heap_trim_s += took
        self.heap_trim_max_s = max(self.heap_trim_max_s, took)
        return True

    def _save_clock(self) -> None:
        """Keep the service clock (woken at once when the wall clock steps: Service._clock_stepped). A full or
        failing disk keeps it in memory until a later pass can write it."""
        try:
            self.clock.save()
        except ServerError as exc:
            log.warning("the service clock could not be saved yet: %s", exc)

    # --- pruning ----------------------------------------------------------------------------------
    def recorded(self, sid: str, reading: Reading) -> None:
        """A session starts recording at `reading` (its created_at is reading.stamp): keep the stamp's lead on
        service time, so its age is service time (the wall clock's steps until then taken out)."""
        self.store.query("INSERT INTO retention (session_id, clock_offset) VALUES (?, ?) ON CONFLICT(session_id) "
                         "DO UPDATE SET clock_offset = excluded.clock_offset", (sid, reading.stamp - reading.service_s))

    def candidates(self) -> list[Candidate]:
        """Sessions whose files may go, oldest first: not live, not pinned, not pruned yet. `recorded_s` is the
        service time they were recorded at: created_at less the stamps' lead on service time then."""
        rows = self.store.query(
            "SELECT s.id, s.created_at - COALESCE(r.clock_offset, 0) AS recorded_s "
            "FROM sessions s LEFT JOIN retention r ON r.session_id = s.id "
            "WHERE s.state != 'live' AND COALESCE(r.pinned, 0) = 0 AND r.pruned_at IS NULL "
            "ORDER BY recorded_s")
        return [Candidate(*r) for r in rows]

    def prune_once(self) -> list[dict]:
        """One pass; returns what it pruned ({id, freed_bytes, reason}). Nothing while a session is live."""
        if not self.policy.active:
            return []
        with self._run_lock:
            now = self.clock.read()
            self.last_run_at = now.stamp
            if self.sessions.live_id() is not None:
                return []
            pruned = []
            # Service time, not the wall clock: a step forward (NTP at boot) ages nothing (server/clock.py).
            cutoff = None if self.policy.keep_days is None else now.service_s - self.policy.keep_days * DAY_S
            used = self.data_bytes(max_age_s=0.0) if self.policy.keep_bytes is not None else 0
            rows = self.candidates()
            # Pruned between sessions, the directory must also hold the next guest's files while they
            # record: keep room for one session as large as the largest of the last few.
            room = self.next_session_bytes(rows) if self.policy.keep_bytes is not None else 0
            for row in rows:
                if cutoff is not None and row.recorded_s < cutoff:
                    reason = f"older than {self.policy.keep_days:g} days"
                elif self.policy.keep_bytes is not None and used + room > self.policy.keep_bytes:
                    reason = (f"data directory over the {self.policy.keep_bytes / GB:g} GB budget with room "
                              f"for the next session ({room / 1e6:.1f} MB)")
                else:
                    # Oldest first: every later session is younger, and the budget is met.
                    break
                # What the prune writes counts too: the kept skeleton file (~27 kB for 16 sensors) and the
                # database's rows (its thinned residuals, the event: ~40 kB of WAL pages). Counted as freed
                # bytes alone, a pass left the directory that much over the room it meant to keep.
                before = self._touched_bytes(row.id)
                try:
                    done = self._prune(row.id, reason)
                except _Downloading:  # its files are being sent: the pass after the download takes them
                    continue
                if done is None:  # a session went live meanwhile: stop, the next gap resumes
                    break
                used += self._touched_bytes(row.id) - before
                pruned.append(done)
            self.over_budget = self.policy.keep_bytes is not None and used > self.policy.keep_bytes
            if pruned:
                self._usage = None
            return pruned

    def next_session_bytes(self, rows: list[Candidate]) -> int:
        """Room to keep for the next session's frames and raw bytes: the largest recording among the
        last ROOM_SESSIONS sessions still on disk, at most ROOM_SHARE of the budget (one long session
        must not clear the whole directory)."""
        mgr = self.sessions
        sizes = [sum(p.stat().st_size for p in (mgr.frames_path(r.id), mgr.raw_path(r.id)) if p.exists())
                 for r in rows[-ROOM_SESSIONS:]]
        return min(max(sizes, default=0), int(ROOM_SHARE * (self.policy.keep_bytes or 0)))

    def _touched_bytes(self, sid: str) -> int:
        """Bytes of the files a prune of `sid` removes or writes: its recordings, its kept skeleton, the
        database with its WAL (two stats each, not a walk of the directory)."""
        mgr, db = self.sessions, self.store.path
        paths = (mgr.frames_path(sid), mgr.raw_path(sid), self.kept_skeleton_path(sid),
                 db, db.with_name(db.name + "-wal"), db.with_name(db.name + "-shm"))
        total = 0
        for path in paths:
            try:
                total += path.stat().st_size
            except FileNotFoundError:
                pass
        return total

    def _prune(self, sid: str, reason: str) -> dict | None:
        mgr = self.sessions
        with mgr._lock:  # no session starts while its predecessor's files go
            if mgr.live_id() is not None:
                return None
            if mgr.holds.claim(sid, lambda: Gone(f"session {sid}'s frames and raw recording were pruned just now "
                                                 f"({reason}); its result, skeleton and events are kept")):
                raise _Downloading(sid)
            try:
                return self._prune_files(sid, reason)
            finally:
                mgr.holds.unclaim(sid)

    def _prune_files(self, sid: str, reason: str) -> dict:
        """Remove the session's frames and raw recording (under the manager's lock, its files claimed)."""
        mgr = self.sessions
        self._keep_skeleton(sid)
        freed = 0
        for path in (mgr.frames_path(sid), mgr.raw_path(sid)):
            try:
                size = path.stat().st_size
                path.unlink()
                freed += size
            except FileNotFoundError:
                pass
        # The 20 Hz residual series is the one bulky row set a pruned session keeps: thinned to 1 Hz
        # (a season of guests would otherwise grow the database by ~0.2 MB each, for good).
        self.store.thin_residuals(sid, PRUNED_RESIDUAL_S)
        now = self.clock.stamp()
        self.store.query(
            "INSERT INTO retention (session_id, pruned_at, freed_bytes, reason) VALUES (?, ?, ?, ?) "
            "ON CONFLICT(session_id) DO UPDATE SET pruned_at = excluded.pruned_at, "
            "freed_bytes = excluded.freed_bytes, reason = excluded.reason", (sid, now, freed, reason))
        self.add_event(Event.new("session", session_id=sid, time_s=None, action="pruned", freed_bytes=freed,
                                 reason=reason,
                                 message=f"session {sid}'s frames and raw recording were pruned ({freed / 1e6:.1f} "
                                         f"MB, {reason}); its result, skeleton and events are kept"))
        log.info("pruned session %s (%.1f MB, %s)", sid, freed / 1e6, reason)
        return {"id": sid, "freed_bytes": freed, "reason": reason}

    def _keep_skeleton(self, sid: str) -> None:
        """Write the session's calibrated skeleton file while its frames are still there."""
        from flockcal.exports.skeleton import skeleton_bytes
        from flockcal.atomic import write_atomic

        path = self.kept_skeleton_path(sid)
        result = self.store.result(sid)
        if result is None or path.exists() or not self.sessions.frames_path(sid).exists():
            return
        try:
            take = self.sessions.take(sid)
            row = self.store.session(sid)
            source = {"session": sid, "performer": row.performer, "take": f"{sid}.npz",
                      "frames": int(take.n_frames), "rate_hz": float(take.rate_hz)}
            write_atomic(path, skeleton_bytes(result, source=source, take=take))
        except Exception as exc:  # a result the exporter cannot draw: /skeleton said so before as well
            log.warning("no skeleton file kept for session %s: %s", sid, exc)

    # --- pins and state ------------------------------------------------------------------------
    def kept_skeleton_path(self, sid: str) -> Path:
        return self.sessions.recordings / f"{sid}{KEPT_SKELETON_SUFFIX}"

    def state(self, sid: str) -> PruneState:
        rows = self.store.query("SELECT pinned, pruned_at, reason FROM retention WHERE session_id = ?", (sid,))
        return _state(*rows[0]) if rows else PruneState()

    def annotate(self, rows: list) -> list:
        """Session rows (store.SessionRow) with their pinned / pruned_at (GET /api/sessions and /api/sessions/{id})."""
        if len(rows) > 1:
            states = {sid: _state(*st) for sid, *st in
                      self.store.query("SELECT session_id, pinned, pruned_at, reason FROM retention")}
            return [replace(row, **states.get(row.id, PruneState())._asdict()) for row in rows]
        return [replace(row, **self.state(row.id)._asdict()) for row in rows]

    def pin(self, sid: str, pinned: bool = True) -> None:
        """Pin (never prune) or unpin a session; a pruned session cannot be pinned back to its frames."""
        st = self.state(sid)
        if pinned and st.pruned_at is not None:
            raise Conflict(f"session {sid} was already pruned ({st.pruned_reason}); its frames are gone, "
                           "so pinning cannot keep them")
        self.store.query(
            "INSERT INTO retention (session_id, pinned) VALUES (?, ?) "
            "ON CONFLICT(session_id) DO UPDATE SET pinned = excluded.pinned", (sid, int(pinned)))
        if not pinned:
            self.wake()

    def forget(self, sid: str) -> None:
        """The session was deleted: its pin and prune record (and kept skeleton) go with it."""
        self.store.query("DELETE FROM retention WHERE session_id = ?", (sid,))
        self.kept_skeleton_path(sid).unlink(missing_ok=True)

    def check_files(self, sid: str, what: str) -> None:
        """Raise 410 Gone when the session's `what` (frames, raw recording) was pruned."""
        st = self.state(sid)
        if st.pruned_at is not None:
            when = time.strftime("%Y-%m-%d %H:%M", time.localtime(st.pruned_at))
            raise Gone(f"session {sid}'s {what} was pruned on {when} ({st.pruned_reason}); its result, "
                       f"skeleton and events are kept. Pin sessions you need whole (POST /api/sessions/{{id}}/pin)")

    def data_bytes(self, max_age_s: float = 5.0) -> int:
        """The data directory's size, walked at most every `max_age_s` (a season leaves tens of thousands of
        small files, and /api/status is polled)."""
        now = self.clock.monotonic()
        if self._usage is None or now - self._usage[0] > max_age_s:
            self._usage = (now, tree_bytes(self.data_dir))
        return self._usage[1]

    def status(self) -> dict:
        """For /api/status: the policy, the disk it governs, what was pruned and pinned."""
        pinned, pruned, freed = self.store.query("SELECT COALESCE(SUM(pinned), 0), COUNT(pruned_at), "
                                                 "COALESCE(SUM(freed_bytes), 0) FROM retention")[0]
        used = self.data_bytes()
        return {
            "enabled": self.policy.active,
            "policy": self.policy.describe(),
            "keep_days": self.policy.keep_days,
            "keep_disk_gb": None if self.policy.keep_bytes is None else self.policy.keep_bytes / GB,
            "data_dir_bytes": used,
            "over_budget": bool(self.over_budget),
            "pinned_sessions": int(pinned),
            "pruned_sessions": int(pruned),
            "freed_bytes": int(freed),
            "last_run_at": self.last_run_at,
            "last_error": self.last_error,
            "heap_trims": self.heap_trims,
            "heap_trim_ms_mean": 1e3 * self.heap_trim_s / self.heap_trims if self.heap_trims else None,
            "heap_trim_ms_max": 1e3 * self.heap_trim_max_s,
        }


def _state(pinned, pruned_at, reason) -> PruneState:
    return PruneState(bool(pinned), pruned_at, reason)


def policy_from(keep_days: float | None, keep_disk_gb: float | None) -> Policy:
    """The policy of `serve --keep-days/--keep-disk` (checked in Settings.check)."""
    return Policy(keep_days=keep_days, keep_bytes=None if keep_disk_gb is None else int(math.floor(keep_disk_gb * GB)))
