"""The systemd unit a kiosk runs flockcal under (docs/kiosk/flockcal.service): it restarts on failure,
never gives up, runs a `flockcal serve` command line this version accepts with retention set, systemd
itself finds nothing wrong with it, and the SIGTERM it stops the service with stores the live session.
"""

from __future__ import annotations

import configparser
import shlex
import shutil
import signal
import sqlite3
import subprocess
import sys
from pathlib import Path

import httpx
import pytest

from flockcal.cli import build_parser
from flockcal.commands.serve import settings_from_args
from server_helpers import ServerProcess, free_port, wait_connected
from service_process import wait_for

UNIT = Path(__file__).resolve().parents[1] / "docs" / "kiosk" / "flockcal.service"


def read_unit(path: Path) -> configparser.ConfigParser:
    unit = configparser.ConfigParser(interpolation=None, strict=False, comment_prefixes=("#", ";"))
    unit.optionxform = str  # systemd keys are case-sensitive
    unit.read_string(path.read_text())
    return unit


def test_unit_restarts_on_failure_forever_and_its_command_line_is_one_serve_accepts():
    unit = read_unit(UNIT)
    service = unit["Service"]
    assert service["Restart"] == "on-failure"
    assert 0 < float(service["RestartSec"]) <= 30
    assert unit["Unit"]["StartLimitIntervalSec"] == "0"  # a burst of crashes must not stop the restarts
    assert service["KillSignal"] == "SIGTERM"
    # Descriptors: not the 1024 a unit gets without saying (1,100 half-sent requests took them all).
    assert int(service["LimitNOFILE"]) >= 4096
    # kiosk.md, "Measured": RSS flat after warm-up only with two malloc arenas.
    assert "MALLOC_ARENA_MAX=2" in shlex.split(service["Environment"])
    argv = shlex.split(service["ExecStart"])
    assert Path(argv[0]).name == "flockcal" and argv[1] == "serve"
    # The options are the ones this version's `serve` takes (the real parser and checks).
    args = build_parser().parse_args(argv[1:])
    settings = settings_from_args(args).check()
    assert settings.keep_days is not None and settings.keep_disk_gb is not None
    assert settings.device == "/dev/ttyUSB0" and str(settings.data_dir) == "/var/lib/flockcal"


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="needs systemd-analyze (package systemd)")
def test_systemd_finds_nothing_wrong_with_the_unit(tmp_path):
    # The unit as installed, with ExecStart pointed at this environment's flockcal (the one path that
    # differs between machines), verified by systemd itself.
    exe = Path(sys.executable).with_name("flockcal")
    assert exe.exists(), f"no flockcal script beside {sys.executable}"
    text = UNIT.read_text().replace("/opt/flockcal/venv/bin/flockcal", str(exe))
    copy = tmp_path / "flockcal.service"
    copy.write_text(text)
    out = subprocess.run(["systemd-analyze", "verify", str(copy)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert "flockcal.service" not in out.stderr, out.stderr


def test_a_damaged_database_exits_with_the_status_the_unit_does_not_restart(tmp_path):
    # What was tried: the unit's serve on a data directory whose database is random bytes. Restarting every
    # 5 s for ever cannot mend it: serve's exit status must be one RestartPreventExitStatus names.
    unit = read_unit(UNIT)
    prevent = shlex.split(unit["Service"]["RestartPreventExitStatus"])
    data = tmp_path / "data"
    data.mkdir()
    (data / "flockcal.sqlite3").write_bytes(bytes(range(256)) * 64)
    out = subprocess.run([sys.executable, "-m", "flockcal", "serve", "--http-port", "0", "--data-dir", str(data),
                          "--device", "sim://unitdb?birds=6&motion=exercise&rate=100", "--birds", "6"],
                         capture_output=True, text=True, timeout=120)
    assert str(out.returncode) in prevent and out.returncode != 0, (out.returncode, prevent, out.stderr)
    assert "damaged" in out.stderr and "Traceback" not in out.stderr


def test_the_units_sigterm_stops_the_live_session_and_stores_its_result(tmp_path):
    # What `systemctl stop` or a restart does: SIGTERM to serve while a guest's session is live.
    data = tmp_path / "data"
    server = ServerProcess(["--device", "sim://unit?birds=6&motion=exercise&rate=100", "--birds", "6",
                            "--data-dir", str(data)], free_port()).start()
    try:
        wait_connected(server.url)
        sid = httpx.post(server.url + "/api/sessions", json={"performer": "guest"}).json()["id"]
        wait_for(lambda: httpx.get(server.url + f"/api/sessions/{sid}").json()["frames"] >= 300, 30,
                 "the session takes 300 frames")
        server.proc.send_signal(signal.SIGTERM)
        # uvicorn shuts down gracefully; serve then prints its stop report and exits 0, which
        # Restart=on-failure leaves stopped.
        assert server.proc.wait(30) == 0  # the same stop path and report as Ctrl-C (tests/test_server_breaks.py)
    finally:
        server.stop()
    with sqlite3.connect(data / "flockcal.sqlite3") as db:
        state, result = db.execute("SELECT state, result FROM sessions WHERE id = ?", (sid,)).fetchone()
    assert state == "stopped" and result is not None
