"""SQLite persistence for sessions, results, events and residual samples (stdlib sqlite3, WAL mode).

One connection guarded by a lock: writes come from the pipeline thread and from request threads.
WAL plus `synchronous=NORMAL` keeps the file readable after a kill -9 and costs little per commit.
A full disk raises InsufficientStorage (507), a damaged file or row DatabaseDamaged (503), never a bare
sqlite3 error; opening checks the file (`PRAGMA quick_check`) so damage is found at start.
"""

from __future__ import annotations

import json
import os
import sqlite3
import threading
from collections.abc import Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from flockcal.errors import FlockcalError
from flockcal.server.errors import DatabaseDamaged, InsufficientStorage, ServerError, Unavailable
from flockcal.server.events import Event
from flockcal.solver.calibration import Calibration
from flockcal.solver.progress import Progress
from flockcal.solver.slippage.monitor import SlipEvent

SCHEMA = """
CREATE TABLE IF NOT EXISTS sessions (
    id TEXT PRIMARY KEY,
    performer TEXT NOT NULL,
    state TEXT NOT NULL,            -- live | stopped | interrupted
    root TEXT,
    hierarchy TEXT,                 -- JSON {child: parent} or NULL (automatic)
    names TEXT NOT NULL,            -- JSON list of sensor names
    device TEXT NOT NULL,
    rate_hz REAL,
    created_at REAL NOT NULL,       -- unix seconds (the service clock's stamp: server/clock.py)
    stopped_at REAL,                -- created_at + duration_s: never before created_at
    frames INTEGER NOT NULL DEFAULT 0,
    recording TEXT,                 -- file name inside the recordings directory
    result TEXT,                    -- the fit as a record (solver/records.py: the Calibration whole, its slips
                                    -- typed); older rows: the JSON of design.md §5. NULL until stopped or re-solved
    note TEXT,
    progress TEXT,                  -- JSON of solver/progress.py's Progress as the session ended (or was re-solved)
    profile TEXT,                   -- stage | kiosk: how it decides it is calibrated (NULL: stage, older sessions)
    duration_s REAL                 -- how long it recorded, on the monotonic clock (NULL: older sessions)
);
CREATE TABLE IF NOT EXISTS events (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    session_id TEXT,
    type TEXT NOT NULL,             -- slip | tracker | session
    time_s REAL,                    -- seconds since session start (NULL outside a session)
    wall_time REAL NOT NULL,
    payload TEXT NOT NULL           -- JSON, type-specific fields
);
CREATE INDEX IF NOT EXISTS events_session ON events (session_id, id);
CREATE TABLE IF NOT EXISTS residuals (
    session_id TEXT NOT NULL,
    time_s REAL NOT NULL,
    rms_mm TEXT NOT NULL            -- JSON {joint child name: rms in mm}
);
CREATE INDEX IF NOT EXISTS residuals_session ON residuals (session_id, time_s);
"""

SESSION_COLUMNS = (
    "id", "performer", "state", "root", "hierarchy", "names", "device", "rate_hz",
    "created_at", "stopped_at", "frames", "recording", "note", "profile", "duration_s",
)


@dataclass(frozen=True)
class SessionRow:
    """A session as the API shows it (`models.Session`): its row, decoded once where it is read, then what
    the session manager adds (its files, its lease, retention's pin and prune; the live session's figures).
    The fields up to `done` are read from the row, in `SESSION_COLUMNS` order; `progress` and `done` are
    its stored progress document's (None before one was kept)."""

    id: str
    performer: str
    state: str  # live | stopped | interrupted
    root: str | None
    hierarchy: dict | None
    names: list
    device: str
    rate_hz: float | None
    created_at: float
    stopped_at: float | None
    frames: int
    recording: str | None
    note: str | None
    profile: str | None
    duration_s: float | None
    has_result: bool
    progress: float | None
    done: bool | None
    has_recording: bool = False
    has_raw_recording: bool = False
    skeleton: str | None = None
    lease_s: float | None = None
    pinned: bool = False
    pruned_at: float | None = None
    pruned_reason: str | None = None


def damaged_message(path: Path, what: str) -> str:
    return (f"the database {path} is damaged ({what}); stop the service, move the file aside "
            f"(mv {path} {path}.damaged, with its -wal and -shm files) and start it again: it makes a new one. "
            "The service never deletes it; `sqlite3 FILE .recover` may get rows back")


def storage_error(exc: sqlite3.Error, path: Path) -> ServerError | None:
    """The service error a sqlite3 error stands for: a full disk, a damaged file, an I/O failure; None for
    anything else (a bug: let it be seen)."""
    code = getattr(exc, "sqlite_errorcode", None)
    primary = None if code is None else code & 0xFF
    if primary == sqlite3.SQLITE_FULL:
        return InsufficientStorage(f"the disk holding the database {path} is full ({exc}); free some space "
                                   "(DELETE old sessions, or make room on that disk) and try again")
    if primary in (sqlite3.SQLITE_CORRUPT, sqlite3.SQLITE_NOTADB) or "malformed JSON" in str(exc):
        # (the last: SQLite's json functions reading a stored payload that is no longer JSON)
        return DatabaseDamaged(damaged_message(path, str(exc)))
    if primary in (sqlite3.SQLITE_IOERR, sqlite3.SQLITE_CANTOPEN) and _disk_full(path):
        # SQLite reports a full disk as an I/O error where it maps its index (-shm) or opens a file.
        return InsufficientStorage(f"the disk holding the database {path} is full ({exc}); make room on it "
                                   "(DELETE old sessions, or free space on that disk) and try again")
    if primary in (sqlite3.SQLITE_IOERR, sqlite3.SQLITE_CANTOPEN, sqlite3.SQLITE_READONLY):
        return Unavailable(f"the database {path} could not be read or written ({exc}); check the disk and "
                           "its permissions", retry_after=10)
    return None


def _disk_full(path: Path) -> bool:
    try:
        st = os.statvfs(path.parent)
    except OSError:
        return False
    return st.f_bavail * st.f_frsize < 2**20


class Store:
    """The service database; every method is one short transaction."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._lock = threading.Lock()
        try:
            self._db = sqlite3.connect(str(self.path), check_same_thread=False, isolation_level=None, timeout=10)
        except sqlite3.Error as exc:
            raise storage_error(exc, self.path) or exc from None
        try:
            with self._guard():
                self._open()
        except BaseException:
            self._db.close()
            raise

    def _open(self) -> None:
        self._db.row_factory = sqlite3.Row
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA synchronous=NORMAL")
        self._db.execute("PRAGMA foreign_keys=ON")
        # Damage is found now, not as a 500 on whichever request first reads a bad page (20 of 27 calls
        # did). quick_check reads every page once: about a second per few hundred MB.
        problems = [r[0] for r in self._db.execute("PRAGMA quick_check(5)")]
        if problems != ["ok"]:
            raise DatabaseDamaged(damaged_message(self.path, "; ".join(problems)[:300]))
        with self._lock:
            self._db.executescript(SCHEMA)
            # Databases made before sessions kept their progress gain the column (empty for old sessions).
            columns = {name for (name,) in self._db.execute("SELECT name FROM pragma_table_info('sessions')")}
            if "progress" not in columns:
                self._db.execute("ALTER TABLE sessions ADD COLUMN progress TEXT")
            # ... and, since sessions chose how they decide they are calibrated, their profile (stage before).
            if "profile" not in columns:
                self._db.execute("ALTER TABLE sessions ADD COLUMN profile TEXT")
            # ... and, since durations are measured (server/clock.py), how long each recorded.
            if "duration_s" not in columns:
                self._db.execute("ALTER TABLE sessions ADD COLUMN duration_s REAL")

    @contextmanager
    def _guard(self):
        """sqlite3 errors of a full disk, a damaged file or a failing disk as the service's errors."""
        try:
            yield
        except sqlite3.Error as exc:
            mapped = storage_error(exc, self.path)
            if mapped is None:
                raise
            raise mapped from None

    def _rollback(self) -> None:
        # SQLite has already rolled back on some errors (a full disk); a second ROLLBACK would raise.
        if self._db.in_transaction:
            self._db.execute("ROLLBACK")

    def _loads(self, text: str, what: str):
        try:
            return json.loads(text)
        except ValueError as exc:
            raise DatabaseDamaged(damaged_message(self.path, f"{what} is not JSON: {exc}")) from None

    def close(self) -> None:
        with self._lock:
            self._db.close()

    def query(self, sql: str, args=()) -> list[sqlite3.Row]:
        """One statement under the store's lock, for modules keeping tables of their own (server/retention.py)."""
        return self._run(sql, args)

    def _run(self, sql: str, args=()) -> list[sqlite3.Row]:
        with self._lock, self._guard():
            return self._db.execute(sql, args).fetchall()

    # --- sessions -----------------------------------------------------------------------------
    def insert_session(self, row: Mapping) -> None:
        """A new session's row from its column values by name (SESSION_COLUMNS)."""
        cols = [c for c in SESSION_COLUMNS if c in row]
        vals = [json.dumps(row[c]) if c in ("hierarchy", "names") and row[c] is not None else row[c] for c in cols]
        self._run(f"INSERT INTO sessions ({', '.join(cols)}) VALUES ({', '.join('?' * len(cols))})", vals)

    def update_session(self, session_id: str, **fields) -> None:
        """Set columns of a session's row: `result` a Calibration (kept whole as its record: solver/records.py),
        `progress` a Progress (its document), others as they are."""
        sets = ", ".join(f"{k} = ?" for k in fields)
        self._run(f"UPDATE sessions SET {sets} WHERE id = ?", [*map(_column, fields.values()), session_id])

    def session(self, session_id: str) -> SessionRow | None:
        rows = self._run(f"{_SESSION_SELECT} WHERE id = ?", (session_id,))
        return self._session_row(rows[0]) if rows else None

    def sessions(self) -> list[SessionRow]:
        rows = self._run(f"{_SESSION_SELECT} ORDER BY created_at DESC")
        return [self._session_row(r) for r in rows]

    def progress(self, session_id: str) -> Progress | None:
        """The progress stored when the session stopped or was re-solved, None before."""
        rows = self._run("SELECT progress FROM sessions WHERE id = ?", (session_id,))
        text = rows[0][0] if rows else None
        if not text:
            return None
        what = f"session {session_id}'s progress"
        try:
            return Progress.from_dict(self._loads(text, what))
        except (KeyError, TypeError, ValueError):
            raise DatabaseDamaged(damaged_message(self.path, f"{what} is not a progress document")) from None

    def result(self, session_id: str) -> Calibration | None:
        """The session's stored fit, decoded once: its record, or (a row stored before records) its §5 object
        read by the one parser, solver/calibration_json.py."""
        rows = self._run("SELECT result FROM sessions WHERE id = ?", (session_id,))
        text = rows[0][0] if rows else None
        return decoded_result(text, self.path, f"session {session_id}'s result") if text else None

    def delete_session(self, session_id: str) -> None:
        with self._lock, self._guard():
            self._db.execute("BEGIN")
            try:
                self._db.execute("DELETE FROM events WHERE session_id = ?", (session_id,))
                self._db.execute("DELETE FROM residuals WHERE session_id = ?", (session_id,))
                self._db.execute("DELETE FROM sessions WHERE id = ?", (session_id,))
                self._db.execute("COMMIT")
            except BaseException:
                self._rollback()
                raise

    def mark_interrupted(self) -> list[str]:
        """Sessions left 'live' by a process that died: mark them interrupted; returns their ids."""
        ids = [sid for (sid,) in self._run("SELECT id FROM sessions WHERE state = 'live'")]
        if ids:
            self._run("UPDATE sessions SET state = 'interrupted', note = ? WHERE state = 'live'",
                      ("the service stopped while this session was live; re-solve it from its recording",))
        return ids

    # --- events and residuals ------------------------------------------------------------------
    def add_events(self, events: list[Event]) -> list[int]:
        """Insert events; returns their ids. An event that has an id keeps it (one held in memory while the
        disk was full, already shown with it)."""
        ids = []
        with self._lock, self._guard():
            self._db.execute("BEGIN")
            try:
                for ev in events:
                    cur = self._db.execute(
                        "INSERT INTO events (id, session_id, type, time_s, wall_time, payload) VALUES (?, ?, ?, ?, ?, ?)",
                        (ev.id, ev.session_id, ev.type, ev.time_s, ev.wall_time, json.dumps(ev.payload)),
                    )
                    ids.append(cur.lastrowid)
                self._db.execute("COMMIT")
            except BaseException:
                self._rollback()
                raise
        return ids

    def last_event_id(self) -> int:
        """The largest event id stored (a read: it works on a full disk)."""
        return int(self._run("SELECT COALESCE(MAX(id), 0) FROM events")[0][0])

    def events(self, session_id: str | None, since_id: int = 0, limit: int | None = 1000) -> list[Event]:
        """Events after `since_id`, oldest first, at most `limit` (None: all of them)."""
        limit = -1 if limit is None else limit  # SQLite: a negative LIMIT is none
        if session_id is None:
            rows = self._run(f"{_EVENT_SELECT} WHERE id > ? ORDER BY id LIMIT ?", (since_id, limit))
        else:
            rows = self._run(f"{_EVENT_SELECT} WHERE session_id = ? AND id > ? ORDER BY id LIMIT ?",
                             (session_id, since_id, limit))
        return [self._event(*r) for r in rows]

    def slips(self, session_id: str, names) -> tuple[SlipEvent, ...]:
        """The session's slip events naming one of `names`, oldest first, as the slip monitor reported them
        (to their stored rounding): what its result lists and a re-solve refits at."""
        from flockcal.solver.calibration_json import event_from_json

        rows = self._run("SELECT time_s, payload FROM events WHERE session_id = ? AND type = 'slip' AND "
                         "json_extract(payload, '$.sensor') IN (SELECT value FROM json_each(?)) ORDER BY id",
                         (session_id, json.dumps(list(names))))
        what = f"a slip event of session {session_id}"
        try:
            return tuple(event_from_json({**self._loads(payload, what), "time_s": t}, names) for t, payload in rows)
        except (FlockcalError, TypeError, ValueError) as exc:
            raise DatabaseDamaged(damaged_message(self.path, f"{what} cannot be read: {exc}")) from None

    def add_residuals(self, session_id: str, samples: list[tuple[float, dict]]) -> None:
        if not samples:
            return
        with self._lock, self._guard():
            self._db.executemany(
                "INSERT INTO residuals (session_id, time_s, rms_mm) VALUES (?, ?, ?)",
                [(session_id, t, json.dumps(v)) for t, v in samples],
            )

    def residuals(self, session_id: str, since: float = float("-inf"), limit: int = 100_000) -> list[tuple[float, dict]]:
        rows = self._run(
            "SELECT time_s, rms_mm FROM residuals WHERE session_id = ? AND time_s > ? ORDER BY time_s LIMIT ?",
            (session_id, since, limit),
        )
        return [(t, self._loads(rms, f"a residual sample of session {session_id}")) for t, rms in rows]

    def thin_residuals(self, session_id: str, every_s: float = 1.0) -> int:
        """Keep one residual sample per `every_s` of a session's time (the first of each), for a session
        whose recordings are pruned: the series still shows how each joint fitted, at a twentieth of the
        rows. Returns the rows removed."""
        with self._lock, self._guard():
            cur = self._db.execute(
                "DELETE FROM residuals WHERE session_id = ? AND rowid NOT IN (SELECT MIN(rowid) FROM residuals "
                "WHERE session_id = ? GROUP BY CAST(time_s / ? AS INTEGER))", (session_id, session_id, float(every_s)))
            return cur.rowcount

    def counts(self) -> dict:
        """Row counts per table (tests use this to see that a bad request changed nothing)."""
        return {t: self._run(f"SELECT COUNT(*) FROM {t}")[0][0] for t in ("sessions", "events", "residuals")}

    def _session_row(self, row: sqlite3.Row) -> SessionRow:
        (sid, performer, state, root, hierarchy, names, device, rate_hz, created_at, stopped_at, frames, recording,
         note, profile, duration_s, has_result, progress, done) = row
        where = f"session {sid!r}"
        hierarchy = self._loads(hierarchy, f"{where}'s hierarchy") if hierarchy else None
        names = self._loads(names, f"{where}'s sensor names")
        if not isinstance(names, list) or not isinstance(sid, str):
            raise DatabaseDamaged(damaged_message(self.path, f"{where}'s row is malformed"))
        if duration_s is None and stopped_at is not None:  # stopped before durations were measured
            duration_s = max(stopped_at - created_at, 0.0)
        return SessionRow(sid, performer, state, root, hierarchy, names, device, rate_hz, created_at, stopped_at,
                          frames, recording, note, profile, duration_s, bool(has_result), progress,
                          None if done is None else bool(done))

    def _event(self, id: int, session_id: str | None, type: str, time_s: float | None, wall_time: float,
               payload: str) -> Event:
        d = self._loads(payload, f"event {id}")
        if not isinstance(d, dict):
            raise DatabaseDamaged(damaged_message(self.path, f"event {id} is not a JSON object"))
        return Event.stored(id, session_id, type, time_s, wall_time, d)


# A session row with its stored progress document's figure and flag (SessionRow's fields in order).
_SESSION_SELECT = (f"SELECT {', '.join(SESSION_COLUMNS)}, result IS NOT NULL, json_extract(progress, '$.progress'), "
                   "json_extract(progress, '$.done') FROM sessions")
_EVENT_SELECT = "SELECT id, session_id, type, time_s, wall_time, payload FROM events"


def _column(value):
    """A value as its column holds it: a fit as its record, a progress as its document, JSON for the rest
    that is not a plain value."""
    if isinstance(value, Calibration):
        from flockcal.solver.records import record_text

        return record_text(value)
    if isinstance(value, Progress):
        value = value.to_dict()
    return json.dumps(value) if isinstance(value, (dict, list)) else value


def decoded_result(text: str, path: Path, what: str) -> Calibration:
    """A stored fit: its record (solver/records.py), or the §5 object a row held before records."""
    from flockcal.solver.calibration_json import calibration_from_json
    from flockcal.solver.records import from_record

    try:
        if text.startswith('{"$record"'):
            return from_record(text, Calibration)
        return calibration_from_json(json.loads(text))
    except (FlockcalError, ValueError, TypeError) as exc:
        raise DatabaseDamaged(damaged_message(path, f"{what} cannot be read: {exc}")) from None
