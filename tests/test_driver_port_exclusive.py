"""The tracker port is held alone and checked before a byte is written to it (drivers/port_guard.py).

Real ptys and real processes throughout: the fake tracker is `flockcal simulate --pty` in a child process (so
it can be killed, leaving its link behind as a crash does), services are `flockcal serve` children, "another
program" is a process of the test's own (a pty it opened, a terminal a child session owns).
"""

from __future__ import annotations

import fcntl
import os
import shutil
import signal
import subprocess
import sys
import termios
import time
import tty
from pathlib import Path

import httpx
import pytest

from flockcal.drivers import uucp_lock
from flockcal.drivers.link import FlockLink
from flockcal.drivers.port_guard import PortChanged, check_port
from server_helpers import free_port
from service_process import Serve, run_serve, wait_for

RATE_HZ = 100.0
BIRDS = 4  # 4 × 15 bytes × 100 Hz: well inside the fake's 115200-baud line, so every frame arrives


class FakeTracker:
    """`flockcal simulate --pty` as a child process: `.link` is the path it prints, `.pid` its PID."""

    def __init__(self):
        self.proc = subprocess.Popen([sys.executable, "-m", "flockcal", "simulate", "--pty", "--model", "human",
                                      "--birds", str(BIRDS), "--rate", str(RATE_HZ)],
                                     stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        self.link = self.proc.stdout.readline().strip()
        assert self.link, "the fake tracker printed no device"
        self.pid = self.proc.pid
        self.pts = os.path.realpath(self.link)

    def kill(self) -> None:
        """SIGKILL: its link and link folder stay behind, as after a crash."""
        self.proc.kill()
        self.proc.wait(10)

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)
        shutil.rmtree(os.path.dirname(self.link), ignore_errors=True)


@pytest.fixture
def fake():
    trk = FakeTracker()
    yield trk
    trk.close()


class Pty:
    """A pty of the test's own; `reuse(path)` opens ptys until the kernel hands out that number again."""

    def __init__(self):
        self.master, self.slave = os.openpty()
        os.set_blocking(self.master, False)
        self.path = os.ttyname(self.slave)

    @staticmethod
    def reuse(path: str, tries: int = 64) -> "Pty":
        spare = []
        try:
            for _ in range(tries):
                p = Pty()
                if p.path == path:
                    return p
                spare.append(p)  # a lower free number: keep it taken until ours comes round
            pytest.skip(f"{path} was not handed out again within {tries} ptys (another program took it)")
        finally:
            for p in spare:
                p.close()

    def written(self) -> bytes:
        """Whatever anyone wrote to the slave end (it arrives here, at the master)."""
        out = b""
        while True:
            try:
                data = os.read(self.master, 65536)
            except (BlockingIOError, OSError):
                return out
            if not data:
                return out
            out += data

    def close(self) -> None:
        for fd in (self.slave, self.master):
            try:
                os.close(fd)
            except OSError:
                pass


def _tty_nr(pid: int) -> int:
    with open(f"/proc/{pid}/stat", "rb") as fh:
        return int(fh.read().rsplit(b")", 1)[1].split()[4])


def _status(srv: Serve) -> dict:
    return httpx.get(srv.url + "/api/status", timeout=10).json()


def _record(port: str, tmp_path: Path, env=None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "flockcal", "record", "--port", port, "--birds", str(BIRDS), "-o",
                           str(tmp_path / "second.fobraw"), "--seconds", "1"],
                          capture_output=True, text=True, timeout=120, env=env)


def test_a_second_opener_is_refused_naming_the_holder_and_the_first_keeps_its_full_rate(fake, tmp_path):
    # Tried, on one fake tracker: a program of ours holding the port before any flockcal (a `flockcal record`
    # must name it), then a service streaming from it while a second `flockcal serve` and a `flockcal record`
    # try to open it. The second opener used to take over the line (the first got 0 frames for 60 s).
    other = subprocess.Popen([sys.executable, "-c", f"import os, time; fd = os.open({fake.pts!r}, os.O_RDWR | "
                              f"os.O_NOCTTY); print('held', flush=True); time.sleep(60)"],
                             stdout=subprocess.PIPE, text=True)
    try:
        assert other.stdout.readline().strip() == "held"
        run = _record(fake.link, tmp_path)
    finally:
        other.kill()
        other.wait(10)
    assert run.returncode == 2 and run.stderr.count("\n") == 1, run.stderr
    assert f"{fake.link} (→ {fake.pts}) is in use by PID {other.pid} (python" in run.stderr

    port = free_port()
    with Serve(["--device", fake.link, "--birds", BIRDS, "--rate", RATE_HZ], port, tmp_path / "first.log") as first:
        wait_for(lambda: _status(first)["frames"] > RATE_HZ, 60, "the first service streaming")
        before, t0 = _status(first), time.monotonic()
        second = run_serve(["--device", fake.link, "--birds", BIRDS, "--data-dir", tmp_path / "second"])
        record = _record(fake.link, tmp_path)
        time.sleep(max(0.0, 3.0 - (time.monotonic() - t0)))  # a window of at least 3 s
        after, t1 = _status(first), time.monotonic()
    holder = f"is in use by PID {first.proc.pid} (flockcal serve --http-port {port} --device {fake.link}"
    for refused in (second, record):
        lines = refused.stderr.strip().splitlines()
        assert refused.returncode == 2 and len(lines) == 1, refused.stderr
        assert f"{fake.link} (→ {fake.pts}) {holder}" in lines[0], lines[0]
        assert "DIP" not in lines[0] and "master" not in lines[0]
    assert not (tmp_path / "second.fobraw").exists()
    # The first service never noticed: every frame of the window arrived (the fake streams 100 Hz by the
    # wall clock; the window's two status reads are each late by at most a poll: 5 % margin), no reconnect.
    rate = (after["frames"] - before["frames"]) / (t1 - t0)
    assert rate >= 0.95 * RATE_HZ, (rate, before, after)
    assert after["reconnects"] == before["reconnects"] == 0
    assert after["dropped_records"] == before["dropped_records"] and after["connected"]


def test_a_service_started_on_a_stale_link_leaves_the_terminal_now_behind_it_alone(fake, tmp_path):
    # Tried: the fake tracker killed (its /tmp/flockcal-fob-*/fob0 link stays), its pts number handed to a new
    # pty that is the controlling terminal of another program's session, then `flockcal serve` and
    # `flockcal record` started on the old link. They used to write start-up commands into that terminal.
    fake.kill()
    pty = Pty.reuse(fake.pts)
    session = subprocess.Popen(["setsid", "-c", sys.executable, "-c", "import time; time.sleep(60)"],
                               stdin=pty.slave, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        wait_for(lambda: _tty_nr(session.pid) != 0, 20, "the other program's session taking the terminal")
        modes = termios.tcgetattr(pty.slave)
        served = run_serve(["--device", fake.link, "--birds", BIRDS, "--data-dir", tmp_path / "data"])
        recorded = _record(fake.link, tmp_path)
        for run in (served, recorded):
            lines = run.stderr.strip().splitlines()
            assert run.returncode == 2 and len(lines) == 1, run.stderr
            assert f"{fake.link} (→ {fake.pts}) is the terminal of PID {session.pid}" in lines[0], lines[0]
            assert "the link is stale" in lines[0] and "nothing was written to it" in lines[0]
        assert pty.written() == b""  # not a byte reached the terminal
        assert termios.tcgetattr(pty.slave) == modes  # nor was it switched to raw mode or another speed
    finally:
        session.kill()
        session.wait(10)
        pty.close()


def test_a_reconnecting_service_writes_nothing_to_a_pty_another_program_now_holds(fake, tmp_path):
    # Tried: a service streaming from the fake tracker, the fake killed mid-stream, and its pts number taken by
    # a pty of another program (this test) while the service keeps trying to reconnect through the old link.
    with Serve(["--device", fake.link, "--birds", BIRDS, "--rate", RATE_HZ], free_port(), tmp_path / "s.log") as srv:
        wait_for(lambda: _status(srv)["frames"] > 0, 60, "the service streaming")
        fake.kill()
        wait_for(lambda: not _status(srv)["connected"], 30, "the service noticing the tracker is gone")
        pty = Pty.reuse(fake.pts)
        try:
            refused = wait_for(lambda: "stale link" in (_status(srv)["last_error"] or ""), 30,
                               "the service refusing the stale link")
            attempts = _status(srv)["reconnects"]
            wait_for(lambda: _status(srv)["reconnects"] > attempts, 30, "another reconnection attempt")
            assert pty.written() == b"", "the service wrote to another program's pty"
            status = _status(srv)
        finally:
            pty.close()
    assert not status["connected"] and "nothing was written to it" in status["last_error"]
    assert f"{fake.link} is a stale link" in status["last_error"] and refused


def test_a_pty_served_by_another_process_than_before_is_refused_on_reconnect(fake):
    # Tried: the fake tracker's link pointed (freshly, so it is not stale) at a pty this test serves: checked
    # as a first open it is a pty like any other; checked against what streamed before (the reader's
    # reconnect), it names both servers and is refused.
    was = check_port(fake.link)
    assert was is not None and was.pty and was.peer_pids == {fake.pid}
    pty = Pty()
    tty.setraw(pty.slave)
    tmp = fake.link + ".test"
    os.symlink(pty.path, tmp)
    os.replace(tmp, fake.link)
    try:
        assert check_port(fake.link).peer_pids == {os.getpid()}
        with pytest.raises(PortChanged) as err:
            check_port(fake.link, expected=was)
        text = str(err.value)
        assert f"is now served by PID {os.getpid()} (" in text and f"not by PID {fake.pid} (flockcal simulate" in text
        assert pty.written() == b""
    finally:
        pty.close()


def test_a_link_made_before_the_pty_it_leads_to_is_stale(tmp_path):
    # Tried: a link to a live pty with its own time set 10 s before the pty was made (what a link left by a
    # program that stopped looks like once its pty number is reused), and the same link made afresh.
    pty = Pty()
    tty.setraw(pty.slave)
    link = tmp_path / "fob0"
    try:
        os.symlink(pty.path, link)
        made = os.stat(pty.path).st_ctime - 10
        os.utime(link, (made, made), follow_symlinks=False)
        with pytest.raises(PortChanged, match=r"is a stale link: it was made 10 s before the pty it leads to"):
            check_port(str(link))
        link.unlink()
        os.symlink(pty.path, link)
        assert check_port(str(link)).device == pty.path
    finally:
        pty.close()


@pytest.mark.skipif(shutil.which("setpriv") is None, reason="needs setpriv (util-linux) to drop CAP_SYS_ADMIN")
def test_an_open_port_is_exclusive_to_programs_that_do_not_lock_and_free_after_close(tmp_path):
    # Tried: a port held by FlockLink, then opened by a child process that takes no lock (TIOCEXCL must refuse
    # it: EBUSY) — as root the child runs without CAP_SYS_ADMIN, which TIOCEXCL lets through; then the same
    # after the link closed (a pty keeps the flag past close unless it is cleared).
    pty = Pty()
    tty.setraw(pty.slave)
    opener = ["setpriv", "--inh-caps=-sys_admin", "--bounding-set=-sys_admin", sys.executable, "-c",
              f"import os\ntry:\n os.close(os.open({pty.path!r}, os.O_RDWR | os.O_NOCTTY)); print('opened')\n"
              f"except OSError as e:\n print(e.strerror)"]
    link = FlockLink(pty.path).open()
    try:
        held = subprocess.run(opener, capture_output=True, text=True, timeout=60)
    finally:
        link.close()
    freed = subprocess.run(opener, capture_output=True, text=True, timeout=60)
    pty.close()
    assert held.stdout.strip() == "Device or resource busy", held
    assert freed.stdout.strip() == "opened", freed


def test_uucp_lock_files_are_made_honoured_and_cleared_when_stale(tmp_path, monkeypatch, caplog):
    # Tried, in a lock folder of the test's: taking a device's lock (HDB format: the PID in ten columns),
    # another process asking for it (refused, naming this PID), a lock left by a process that is gone and one
    # holding garbage (both taken over), and a lock folder that does not exist (opened without a lock, said).
    monkeypatch.setenv(uucp_lock.LOCK_DIR_VARIABLE, str(tmp_path))
    device = "/dev/ttyFLOCK9"
    path = uucp_lock.acquire(device)
    assert path == tmp_path / "LCK..ttyFLOCK9" and path.read_bytes() == f"{os.getpid():10d}\n".encode()
    probe = ("from flockcal.drivers import uucp_lock\ntry:\n uucp_lock.acquire('/dev/ttyFLOCK9'); print('taken')\n"
             "except uucp_lock.LockHeld as e:\n print('held by', e.pid)")
    other = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=60,
                           env=dict(os.environ, **{uucp_lock.LOCK_DIR_VARIABLE: str(tmp_path)}))
    assert other.stdout.strip() == f"held by {os.getpid()}", other
    uucp_lock.release(path)
    assert not path.exists()

    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    for stale in (f"{gone.pid:10d}\n".encode(), b"not a pid\n"):
        path.write_bytes(stale)
        assert uucp_lock.acquire(device) == path and uucp_lock.read_pid(path) == os.getpid()
        uucp_lock.release(path)

    monkeypatch.setenv(uucp_lock.LOCK_DIR_VARIABLE, str(tmp_path / "missing"))
    with caplog.at_level("WARNING", logger="flockcal.drivers.uucp_lock"):
        assert uucp_lock.acquire(device) is None
    assert "cannot create the lock file" in caplog.text and "no such folder" in caplog.text


@pytest.mark.skipif(not os.path.exists("/dev/ttyS0"), reason="needs a serial device node (/dev/ttyS0)")
def test_a_serial_device_locked_by_a_live_program_is_refused_before_it_is_opened(tmp_path):
    # Tried: /dev/ttyS0's UUCP lock (in a lock folder of the test's) naming a live `sleep`, then `flockcal
    # record` on it: refused by the lock file alone, the device never opened.
    holder = subprocess.Popen(["sleep", "60"])
    try:
        (tmp_path / "LCK..ttyS0").write_bytes(f"{holder.pid:10d}\n".encode())
        run = _record("/dev/ttyS0", tmp_path, env=dict(os.environ, **{uucp_lock.LOCK_DIR_VARIABLE: str(tmp_path)}))
    finally:
        holder.kill()
        holder.wait(10)
    assert run.returncode == 2 and run.stderr.count("\n") == 1, run.stderr
    assert (f"/dev/ttyS0 is locked by PID {holder.pid} (sleep 60) (lock file {tmp_path}/LCK..ttyS0)"
            in run.stderr), run.stderr
