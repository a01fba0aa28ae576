"""Damaged files under the service (issue #37): recordings damaged on disk answer a 4xx with a message and no
download breaks off; a database of random bytes stops the start, and damage found later answers 503, not 500.
A real `flockcal serve` in a child process on loopback (tests/service_process.py).
"""

from __future__ import annotations

import io
import json
import shutil
import sqlite3
from pathlib import Path

import httpx
import numpy as np
import pytest

from break_probes import sim6
from server_helpers import free_port
from service_process import Serve, run_serve, wait_for

# --- damaged recordings --------------------------------------------------------------------------------
def record_sessions(url: str, n: int) -> list[str]:
    ids = []
    for k in range(n):
        sid = httpx.post(url + "/api/sessions", json={"performer": f"guest{k}"}).json()["id"]
        wait_for(lambda: httpx.get(url + f"/api/sessions/{sid}").json()["frames"] >= 300, 60.0, "300 frames")
        assert httpx.post(url + f"/api/sessions/{sid}/stop", timeout=60).status_code == 200
        ids.append(sid)
    return ids


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> tuple[Path, list[str]]:
    """A data directory holding three sessions recorded and stopped by a real serve, and their ids: each test
    damages a copy of its own (recording them once keeps the module short)."""
    data = tmp_path_factory.mktemp("recorded") / "data"
    with Serve(sim6("recorded") + ["--data-dir", data], free_port(), data.parent / "serve.log") as srv:
        ids = record_sessions(srv.url, 3)
        assert srv.stop() in (0, 130)  # Ctrl-C: 0 or 130 by uvicorn version (docs/cli.md)
    return data, ids


def copy_of(recorded, tmp_path: Path) -> tuple[Path, list[str]]:
    data = tmp_path / "data"
    shutil.copytree(recorded[0], data)
    return data, list(recorded[1])


def test_damaged_recordings_answer_a_4xx_with_a_message_and_no_download_breaks_off(recorded, tmp_path):
    """What was tried: a `.frames` cut inside its header, a `.fobraw` cut to 10 bytes, and 20 kB of random bytes
    in the middle of a `.frames` (resolve answered 500 and /bvh broke off after its 200 before). Every call
    answers 2xx, 4xx or 503, never 500; a 200 is a whole file; a 4xx says what is wrong."""
    data, (cut_header, cut_raw, noisy) = copy_of(recorded, tmp_path)
    rec = data / "recordings"
    # Damaged before the service starts: its start must not mind them either.
    (rec / f"{cut_header}.frames").write_bytes((rec / f"{cut_header}.frames").read_bytes()[:40])
    (rec / f"{cut_raw}.fobraw").write_bytes((rec / f"{cut_raw}.fobraw").read_bytes()[:10])
    body = bytearray((rec / f"{noisy}.frames").read_bytes())
    mid = len(body) // 2
    body[mid:mid + 20_000] = np.random.default_rng(37).integers(0, 256, 20_000, dtype=np.uint8).tobytes()
    (rec / f"{noisy}.frames").write_bytes(bytes(body))
    with Serve(sim6("damrec") + ["--data-dir", data], free_port(), tmp_path / "serve.log") as srv:
        for sid in (cut_header, cut_raw, noisy):
            for method, what in (("POST", "resolve"), ("GET", "take"), ("GET", "bvh"), ("GET", "skeleton"),
                                 ("GET", "raw")):
                with httpx.stream(method, srv.url + f"/api/sessions/{sid}/{what}", timeout=120) as r:
                    content = r.read()  # raises if the body breaks off
                    assert r.status_code != 500 and r.status_code < 600, (sid, what, r.status_code, content[:300])
                    if r.status_code >= 400:
                        assert r.status_code in (409, 410, 503) and json.loads(content)["detail"], (sid, what)
                        continue
                if what == "take":
                    with np.load(io.BytesIO(content)) as take:
                        assert take["valid"].shape[0] == take["times"].shape[0] > 0
                        assert np.isfinite(take["positions"]).all() and (np.diff(take["times"]) >= 0).all()
                elif what == "bvh":
                    text = content.decode()
                    stated = int(text.split("Frames:")[1].split()[0])
                    motion = text.split("Frame Time:")[1].strip().splitlines()[1:]
                    assert len(motion) == stated and "nan" not in text.lower(), (sid, stated, len(motion))
        r = httpx.post(srv.url + f"/api/sessions/{cut_header}/resolve")
        assert r.status_code == 409 and "cannot be read" in r.json()["detail"] and f"{cut_header}.frames" in r.json()["detail"]
        # The random bytes cost only the frames they hit: the rest still fits.
        r = httpx.post(srv.url + f"/api/sessions/{noisy}/resolve", timeout=120)
        assert r.status_code == 200 and r.json()["has_result"], r.text
    assert "Traceback" not in srv.output()


# --- a damaged database --------------------------------------------------------------------------------
def test_a_database_of_random_bytes_stops_the_start_with_its_own_exit_status_and_is_kept(tmp_path):
    """What was tried: a flockcal.sqlite3 of random bytes (a traceback and exit 1 before, restarted every 5 s
    for ever by the unit): one line naming the file and what to do, exit 4, the file untouched."""
    data = tmp_path / "data"
    data.mkdir()
    db = data / "flockcal.sqlite3"
    junk = np.random.default_rng(1).integers(0, 256, 65536, dtype=np.uint8).tobytes()
    db.write_bytes(junk)
    out = run_serve(sim6("junkdb") + ["--data-dir", data])
    line = out.stderr.strip()
    assert out.returncode == 4 and "\n" not in line and "Traceback" not in line, out.stderr
    assert str(db) in line and "damaged" in line and "move the file aside" in line, line
    assert db.read_bytes() == junk


def pages_overwritten(db: Path, seed: int) -> None:
    """Overwrite every page but the first (the header) with random bytes, as a failing disk might."""
    raw = bytearray(db.read_bytes())
    page = int.from_bytes(raw[16:18], "big") or 65536
    rng = np.random.default_rng(seed)
    for start in range(page, len(raw), page):
        raw[start:start + page] = rng.integers(0, 256, min(page, len(raw) - start), dtype=np.uint8).tobytes()
    db.write_bytes(bytes(raw))


CALLS = [("GET", "/api/status"), ("GET", "/api/sessions"), ("GET", "/api/sessions/presets"), ("GET", "/api/events"),
         ("GET", "/api/stats"), ("GET", "/api/skeletons"), ("GET", "/api/sessions/{id}"),
         ("GET", "/api/sessions/{id}/progress"), ("GET", "/api/sessions/{id}/result"),
         ("GET", "/api/sessions/{id}/residuals"), ("GET", "/api/sessions/{id}/events"),
         ("GET", "/api/sessions/{id}/take"), ("GET", "/api/sessions/{id}/raw"), ("GET", "/api/sessions/{id}/skeleton"),
         ("GET", "/api/sessions/{id}/bvh"), ("POST", "/api/sessions/{id}/resolve"), ("POST", "/api/sessions/{id}/pin"),
         ("DELETE", "/api/sessions/{id}/pin"), ("POST", "/api/sessions/{id}/stop"), ("GET", "/api/sessions/{other}"),
         ("GET", "/api/sessions/{other}/result"), ("GET", "/api/sessions/{other}/events"),
         ("GET", "/api/sessions/{other}/progress"), ("POST", "/api/sessions"), ("POST", "/api/sessions/{new}/stop"),
         ("DELETE", "/api/sessions/{other}"), ("GET", "/")]


def call_everything(url: str, sid: str, other: str) -> list[tuple[str, str, int, str]]:
    """The 27 calls of the issue's probe; (method, path, status, detail) of each."""
    out, new = [], "none"
    for method, path in CALLS:
        path = path.format(id=sid, other=other, new=new)
        body = {"performer": "next"} if path == "/api/sessions" else None
        r = httpx.request(method, url + path, json=body, timeout=120)
        if path == "/api/sessions" and r.status_code == 201:
            new = r.json()["id"]
            wait_for(lambda: httpx.get(url + f"/api/sessions/{new}").json()["frames"] > 0, 60.0, "frames")
        detail = r.json().get("detail", "") if r.headers.get("content-type", "").startswith("application/json") \
            and r.status_code >= 400 else ""
        out.append((method, path, r.status_code, detail))
        if r.status_code == 503:
            assert int(r.headers["retry-after"]) > 0, (method, path)
    return out


def test_a_damaged_database_is_found_at_start_and_damage_found_later_answers_503_not_500(recorded, tmp_path):
    """What was tried: (a) a real database whose data pages were overwritten: the start refuses it (exit 4)
    instead of serving 20 of 27 calls as 500; (b) rows whose stored JSON was overwritten (a damage the file's
    own check cannot see): the service starts, and of the 27 calls none answers 500, those reading the rows
    answer 503 naming the database and what to do; (c) data pages overwritten while the service runs:
    none of the 27 calls answers 500."""
    data, (sid, other, _) = copy_of(recorded, tmp_path)
    db = data / "flockcal.sqlite3"
    good = db.read_bytes()

    pages_overwritten(db, seed=5)
    out = run_serve(sim6("dbdmg2") + ["--data-dir", data])
    assert out.returncode == 4 and str(db) in out.stderr and "Traceback" not in out.stderr, out.stderr

    db.write_bytes(good)
    with sqlite3.connect(db) as con:
        con.execute("UPDATE sessions SET result = '{\"sensors\": [', progress = 'not json' WHERE id = ?", (sid,))
        con.execute("UPDATE events SET payload = x'ff00ff' WHERE session_id = ?", (sid,))
    with Serve(sim6("dbdmg3") + ["--data-dir", data], free_port(), tmp_path / "serve2.log") as srv:
        calls = call_everything(srv.url, sid, other)
        assert not [c for c in calls if c[2] >= 500 and c[2] != 503], calls
        damaged = [c for c in calls if c[2] == 503]
        assert damaged and all("damaged" in c[3] and str(db) in c[3] for c in damaged), damaged
        assert dict(((m, p), s) for m, p, s, _ in calls)[("GET", f"/api/sessions/{other}/result")] == 200

        # (c) the file damaged under the running service.
        pages_overwritten(db, seed=6)
        later = call_everything(srv.url, other, sid)
        assert not [c for c in later if c[2] >= 500 and c[2] != 503], later
        assert srv.proc.poll() is None
    assert "Traceback" not in srv.output()
