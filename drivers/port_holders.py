"""Who holds a serial device, read from /proc in one walk: the processes with it open, the holders of a
lock on it (/proc/locks), the processes serving a pty's other end, and those whose controlling terminal
it is. Linux only; elsewhere, or where /proc hides other users' processes, the sets come back smaller.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field

PTY_MAJORS = range(136, 144)  # Unix98 pty slaves (/dev/pts/N)
_PTMX = ("/dev/ptmx", "/dev/pts/ptmx")
COMMAND_WIDTH = 80


@dataclass(frozen=True)
class Process:
    """A process as a person recognises it: its PID and its command line, shortened."""

    pid: int
    command: str

    def __str__(self) -> str:
        return f"PID {self.pid} ({self.command})"


@dataclass
class DeviceUse:
    """What /proc says about one device node."""

    open_by: set[int] = field(default_factory=set)  # processes with the node open
    locked_by: set[int] = field(default_factory=set)  # holders of a flock/fcntl lock on its inode
    pty_peer: set[int] = field(default_factory=set)  # a pty: the processes holding its master end
    terminal_of: set[int] = field(default_factory=set)  # processes whose controlling terminal it is


def is_pty(rdev: int) -> bool:
    return os.major(rdev) in PTY_MAJORS


def device_use(path: str, st: os.stat_result) -> DeviceUse:
    """Who uses the character device `path` (its real path; `st` its stat), in one walk over /proc."""
    use = DeviceUse(locked_by=_lock_holders(st))
    major, minor = os.major(st.st_rdev), os.minor(st.st_rdev)
    pty_index = minor + 256 * (major - PTY_MAJORS.start) if is_pty(st.st_rdev) else None
    try:
        pids = [int(p) for p in os.listdir("/proc") if p.isdigit()]
    except OSError:
        return use
    for pid in pids:
        if _tty_of(pid) == (major, minor):
            use.terminal_of.add(pid)
        try:
            fds = os.listdir(f"/proc/{pid}/fd")
        except OSError:  # gone, or another user's
            continue
        for fd in fds:
            try:
                target = os.readlink(f"/proc/{pid}/fd/{fd}")
            except OSError:
                continue
            if target == path:
                use.open_by.add(pid)
            elif pty_index is not None and target in _PTMX and _tty_index(pid, fd) == pty_index:
                use.pty_peer.add(pid)
    return use


def describe(pid: int) -> Process:
    """The process `pid` with its command line (`python -m X …` and `python script …` shown as `X …`)."""
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as fh:
            argv = [a.decode("utf-8", "replace") for a in fh.read().split(b"\0") if a]
    except OSError:
        argv = []
    if not argv:
        try:
            with open(f"/proc/{pid}/comm", encoding="utf-8", errors="replace") as fh:
                argv = [fh.read().strip() or "?"]
        except OSError:
            argv = ["?"]
    if os.path.basename(argv[0]).startswith("python") and len(argv) > 1:
        if argv[1] == "-m" and len(argv) > 2:
            argv = argv[2:]
        elif not argv[1].startswith("-"):
            argv = argv[1:]
    argv[0] = os.path.basename(argv[0])
    text = " ".join(argv)
    if len(text) > COMMAND_WIDTH:
        text = text[: COMMAND_WIDTH - 1] + "…"
    return Process(pid, text)


def alive(pid: int) -> bool:
    """Whether a process `pid` exists (another user's counts)."""
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _tty_of(pid: int) -> tuple[int, int] | None:
    """(major, minor) of the process's controlling terminal; None if it has none."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as fh:
            fields = fh.read().rsplit(b")", 1)[1].split()
        tty_nr = int(fields[4])  # field 7 of proc(5); the command name before it may hold spaces
    except (OSError, IndexError, ValueError):
        return None
    if tty_nr == 0:
        return None
    return (tty_nr >> 8) & 0xFFF, (tty_nr & 0xFF) | ((tty_nr >> 12) & 0xFFF00)


def _tty_index(pid: int, fd: str) -> int | None:
    """The pty number an open /dev/ptmx descriptor serves (fdinfo's tty-index, Linux 4.19 on)."""
    try:
        with open(f"/proc/{pid}/fdinfo/{fd}", encoding="ascii", errors="replace") as fh:
            for line in fh:
                if line.startswith("tty-index:"):
                    return int(line.split()[1])
    except (OSError, ValueError, IndexError):
        pass
    return None


def _lock_holders(st: os.stat_result) -> set[int]:
    """PIDs holding a lock (flock, POSIX, or OFD where it names one) on the inode `st` describes."""
    want = f"{os.major(st.st_dev):02x}:{os.minor(st.st_dev):02x}:{st.st_ino}"
    out = set()
    try:
        with open("/proc/locks", encoding="ascii", errors="replace") as fh:
            for line in fh:
                parts = line.split()
                if len(parts) < 6 or parts[1] == "->":  # a waiter, not a holder
                    continue
                if parts[5] == want and parts[4].isdigit() and int(parts[4]) > 0:
                    out.add(int(parts[4]))
    except OSError:
        pass
    return out
