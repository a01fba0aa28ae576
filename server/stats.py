"""The operator's view of a season: sessions, finished calibrations, time to calibrate and slips per day,
and the disk the data directory takes, from the store alone (GET /api/stats, the dashboard's season panel).
"""

from __future__ import annotations

import shutil
import statistics
import time
from pathlib import Path
from typing import NamedTuple

from flockcal.server.retention import GB, tree_bytes

# Days are the service machine's local calendar days: a kiosk's day is the venue's opening day.
_DAY = "date({col}, 'unixepoch', 'localtime')"


class _Session(NamedTuple):
    id: str
    day: str
    state: str
    calibrated_s: float | None  # session time of its first `calibrated` event; None: never calibrated


def season(store, data_dir: Path, days: int = 14, keep_bytes: int | None = None, now: float | None = None) -> dict:
    """Per-day figures for the last `days` days (today included, newest first) and their totals; `keep_bytes`:
    retention's budget (`serve --keep-disk`), if any."""
    now = time.time() if now is None else now
    since = now - days * 86400.0
    # A session counts as finished when the service said it was calibrated (the `calibrated` event,
    # written the moment progress reached done); its first such event's time_s is its time to calibrate.
    rows = [_Session(*r) for r in store.query(
        f"SELECT s.id, {_DAY.format(col='s.created_at')} AS day, s.state, c.t AS calibrated_s "
        "FROM sessions s LEFT JOIN (SELECT session_id, MIN(time_s) AS t FROM events WHERE type = 'session' "
        "AND json_extract(payload, '$.action') = 'calibrated' GROUP BY session_id) c ON c.session_id = s.id "
        "WHERE s.created_at >= ?", (since,))]
    slips = {day: n for day, n in store.query(
        f"SELECT {_DAY.format(col='wall_time')} AS day, COUNT(*) AS n FROM events WHERE type = 'slip' "
        "AND wall_time >= ? GROUP BY day", (since,))}
    by_day: dict[str, list] = {}
    for r in rows:
        by_day.setdefault(r.day, []).append(r)
    out = []
    for k in range(days):
        day = time.strftime("%Y-%m-%d", time.localtime(now - k * 86400.0))
        out.append(_figures(by_day.get(day, []), slips.get(day, 0), day=day))
    total = _figures(rows, sum(slips.values()))
    usage = shutil.disk_usage(data_dir)
    db = sum(p.stat().st_size for p in Path(data_dir).glob("flockcal.sqlite3*") if p.is_file())
    recordings = tree_bytes(Path(data_dir) / "recordings")
    return {
        "days": out,
        "total": total,
        "window_days": days,
        "timezone": time.strftime("%Z", time.localtime(now)),
        "disk": {"data_dir_bytes": tree_bytes(Path(data_dir)), "database_bytes": db, "recordings_bytes": recordings,
                 "free_bytes": usage.free, "disk_bytes": usage.total,
                 "budget_bytes": None if keep_bytes is None else int(keep_bytes / GB * 1e9)},
    }


def _figures(rows: list[_Session], slips: int, day: str | None = None) -> dict:
    ended = [r for r in rows if r.state != "live"]
    times = [float(r.calibrated_s) for r in rows if r.calibrated_s is not None]
    finished = sum(1 for r in ended if r.calibrated_s is not None)
    out = {"sessions": len(rows), "ended": len(ended), "finished": finished,
           "finished_share": round(finished / len(ended), 4) if ended else None,
           "median_calibration_s": round(statistics.median(times), 2) if times else None,
           "slips": int(slips)}
    return {"day": day, **out} if day is not None else out
