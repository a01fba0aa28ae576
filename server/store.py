"""SQLite persistence for sessions, results, events and residual samples (stdlib sqlite3, WAL mode).

One connection guarded by a lock: writes come from the pipeline thread and from request threads.
WAL plus `synchronous=NORMAL` keeps the file readable after a kill -9 and costs little per commit.
"""

from __future__ import annotations

import json
import sqlite3
import threading
import time
from pathlib import Path

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
    created_at REAL NOT NULL,       -- unix seconds
    stopped_at REAL,
    frames INTEGER NOT NULL DEFAULT 0,
    recording TEXT,                 -- file name inside the recordings directory
    result TEXT,                    -- JSON of design.md §5, NULL until stopped or re-solved
    note TEXT,
    progress TEXT,                  -- JSON of server/progress.py as the session ended (or was re-solved)
    profile TEXT                    -- stage | kiosk: how it decides it is calibrated (NULL: stage, older sessions)
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
    "created_at", "stopped_at", "frames", "recording", "note", "profile",
)


class Store:
    """The service database; every method is one short transaction."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._lock = threading.Lock()
        self._db = sqlite3.connect(str(self.path), check_same_thread=False, isolation_level=None, timeout=10)
        self._db.row_factory = sqlite3.Row
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA synchronous=NORMAL")
        self._db.execute("PRAGMA foreign_keys=ON")
        with self._lock:
            self._db.executescript(SCHEMA)
            # Databases made before sessions kept their progress gain the column (empty for old sessions).
            columns = {r["name"] for r in self._db.execute("PRAGMA table_info(sessions)")}
            if "progress" not in columns:
                self._db.execute("ALTER TABLE sessions ADD COLUMN progress TEXT")
            # ... and, since sessions chose how they decide they are calibrated, their profile (stage before).
            if "profile" not in columns:
                self._db.execute("ALTER TABLE sessions ADD COLUMN profile TEXT")

    def close(self) -> None:
        with self._lock:
            self._db.close()

    def query(self, sql: str, args=()) -> list[sqlite3.Row]:
        """One statement under the store's lock, for modules keeping tables of their own (server/retention.py)."""
        return self._run(sql, args)

    def _run(self, sql: str, args=()) -> list[sqlite3.Row]:
        with self._lock:
            return self._db.execute(sql, args).fetchall()

    # --- sessions -----------------------------------------------------------------------------
    def insert_session(self, row: dict) -> None:
        cols = [c for c in SESSION_COLUMNS if c in row]
        vals = [json.dumps(row[c]) if c in ("hierarchy", "names") and row[c] is not None else row[c] for c in cols]
        self._run(f"INSERT INTO sessions ({', '.join(cols)}) VALUES ({', '.join('?' * len(cols))})", vals)

    def update_session(self, session_id: str, **fields) -> None:
        for key in ("result", "progress"):
            if key in fields and fields[key] is not None and not isinstance(fields[key], str):
                fields[key] = json.dumps(fields[key])
        sets = ", ".join(f"{k} = ?" for k in fields)
        self._run(f"UPDATE sessions SET {sets} WHERE id = ?", [*fields.values(), session_id])

    def session(self, session_id: str) -> dict | None:
        rows = self._run(f"SELECT {', '.join(SESSION_COLUMNS)}, result IS NOT NULL AS has_result, progress "
                         "FROM sessions WHERE id = ?", (session_id,))
        return _session_dict(rows[0]) if rows else None

    def sessions(self) -> list[dict]:
        rows = self._run(f"SELECT {', '.join(SESSION_COLUMNS)}, result IS NOT NULL AS has_result, progress "
                         "FROM sessions ORDER BY created_at DESC")
        return [_session_dict(r) for r in rows]

    def progress(self, session_id: str) -> dict | None:
        """The progress document stored when the session stopped or was re-solved, None before."""
        rows = self._run("SELECT progress FROM sessions WHERE id = ?", (session_id,))
        return json.loads(rows[0]["progress"]) if rows and rows[0]["progress"] else None

    def result(self, session_id: str) -> dict | None:
        rows = self._run("SELECT result FROM sessions WHERE id = ?", (session_id,))
        return json.loads(rows[0]["result"]) if rows and rows[0]["result"] else None

    def delete_session(self, session_id: str) -> None:
        with self._lock:
            self._db.execute("BEGIN")
            try:
                self._db.execute("DELETE FROM events WHERE session_id = ?", (session_id,))
                self._db.execute("DELETE FROM residuals WHERE session_id = ?", (session_id,))
                self._db.execute("DELETE FROM sessions WHERE id = ?", (session_id,))
                self._db.execute("COMMIT")
            except BaseException:
                self._db.execute("ROLLBACK")
                raise

    def mark_interrupted(self) -> list[str]:
        """Sessions left 'live' by a process that died: mark them interrupted; returns their ids."""
        ids = [r["id"] for r in self._run("SELECT id FROM sessions WHERE state = 'live'")]
        if ids:
            self._run("UPDATE sessions SET state = 'interrupted', note = ? WHERE state = 'live'",
                      ("the service stopped while this session was live; re-solve it from its recording",))
        return ids

    # --- events and residuals ------------------------------------------------------------------
    def add_events(self, events: list[dict]) -> list[int]:
        """Insert events ({session_id, type, time_s, wall_time, …payload}); returns their ids."""
        ids = []
        with self._lock:
            self._db.execute("BEGIN")
            try:
                for ev in events:
                    payload = {k: v for k, v in ev.items() if k not in ("id", "session_id", "type", "time_s", "wall_time")}
                    cur = self._db.execute(
                        "INSERT INTO events (session_id, type, time_s, wall_time, payload) VALUES (?, ?, ?, ?, ?)",
                        (ev.get("session_id"), ev["type"], ev.get("time_s"), ev.get("wall_time", time.time()), json.dumps(payload)),
                    )
                    ids.append(cur.lastrowid)
                self._db.execute("COMMIT")
            except BaseException:
                self._db.execute("ROLLBACK")
                raise
        return ids

    def events(self, session_id: str | None, since_id: int = 0, limit: int | None = 1000) -> list[dict]:
        """Events after `since_id`, oldest first, at most `limit` (None: all of them)."""
        limit = -1 if limit is None else limit  # SQLite: a negative LIMIT is none
        if session_id is None:
            rows = self._run("SELECT * FROM events WHERE id > ? ORDER BY id LIMIT ?", (since_id, limit))
        else:
            rows = self._run("SELECT * FROM events WHERE session_id = ? AND id > ? ORDER BY id LIMIT ?", (session_id, since_id, limit))
        return [_event_dict(r) for r in rows]

    def add_residuals(self, session_id: str, samples: list[tuple[float, dict]]) -> None:
        if not samples:
            return
        with self._lock:
            self._db.executemany(
                "INSERT INTO residuals (session_id, time_s, rms_mm) VALUES (?, ?, ?)",
                [(session_id, t, json.dumps(v)) for t, v in samples],
            )

    def residuals(self, session_id: str, since: float = float("-inf"), limit: int = 100_000) -> list[tuple[float, dict]]:
        rows = self._run(
            "SELECT time_s, rms_mm FROM residuals WHERE session_id = ? AND time_s > ? ORDER BY time_s LIMIT ?",
            (session_id, since, limit),
        )
        return [(r["time_s"], json.loads(r["rms_mm"])) for r in rows]

    def thin_residuals(self, session_id: str, every_s: float = 1.0) -> int:
        """Keep one residual sample per `every_s` of a session's time (the first of each), for a session
        whose recordings are pruned: the series still shows how each joint fitted, at a twentieth of the
        rows. Returns the rows removed."""
        with self._lock:
            cur = self._db.execute(
                "DELETE FROM residuals WHERE session_id = ? AND rowid NOT IN (SELECT MIN(rowid) FROM residuals "
                "WHERE session_id = ? GROUP BY CAST(time_s / ? AS INTEGER))", (session_id, session_id, float(every_s)))
            return cur.rowcount

    def counts(self) -> dict:
        """Row counts per table (tests use this to see that a bad request changed nothing)."""
        return {t: self._run(f"SELECT COUNT(*) AS n FROM {t}")[0]["n"] for t in ("sessions", "events", "residuals")}


def _session_dict(row: sqlite3.Row) -> dict:
    d = dict(row)
    d["hierarchy"] = json.loads(d["hierarchy"]) if d["hierarchy"] else None
    d["names"] = json.loads(d["names"])
    d["has_result"] = bool(d["has_result"])
    doc = json.loads(d.pop("progress")) if d.get("progress") else None
    d["progress"] = doc["progress"] if doc else None
    d["done"] = doc["done"] if doc else None
    return d


def _event_dict(row: sqlite3.Row) -> dict:
    d = json.loads(row["payload"])
    d.update(id=row["id"], session_id=row["session_id"], type=row["type"], time_s=row["time_s"], wall_time=row["wall_time"])
    return d
