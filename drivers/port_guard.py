"""Holding a tracker's serial port alone, and making sure it still leads to the tracker before a byte is
written: nobody else holds it (flock, TIOCEXCL, the UUCP lock file, /proc), it is nobody's terminal, a
symlink to a pty is not older than the pty, and a pty is served by whoever served it when it streamed.

Every refusal is one line naming the port and, where /proc shows it, the process in the way.
"""

from __future__ import annotations

import os
import stat
from dataclasses import dataclass

from flockcal.drivers import uucp_lock
from flockcal.drivers.errors import TrackerError
from flockcal.drivers.port_holders import Process, describe, device_use, is_pty

# A symlink to a pty made before the pty existed was left by a program that stopped; the pty's number was
# reused since. The margin covers a link made in the same tick as its pty (and a chmod just after).
STALE_LINK_MARGIN_S = 1.0


class PortBusy(TrackerError):
    """Another program holds the port."""


class PortChanged(TrackerError):
    """The port no longer leads to the tracker (a stale link, another program's terminal or pty)."""


@dataclass(frozen=True)
class PortIdentity:
    """What a device path led to when it was checked: the device node, and for a pty who served it."""

    device: str  # the real path of the node (/dev/pts/3, /dev/ttyUSB0)
    rdev: int
    pty: bool
    peer: tuple[Process, ...] = ()  # a pty: the processes holding its other (master) end

    @property
    def peer_pids(self) -> frozenset[int]:
        return frozenset(p.pid for p in self.peer)


def device_path(url: str) -> str | None:
    """The local path a port URL names, or None for pyserial URLs with a scheme (socket://, rfc2217://,
    sim://, loop://), which are not device nodes."""
    return None if "://" in url else url


def check_port(url: str, expected: PortIdentity | None = None) -> PortIdentity | None:
    """The device behind `url`, checked before it is opened: PortBusy when another program holds it,
    PortChanged when it is not (or no longer) the tracker's (`expected`: what it was when it last streamed).
    None for URLs that are not character devices (pyserial's open reports those, as before)."""
    path = device_path(url)
    if path is None:
        return None
    real = os.path.realpath(path)
    try:
        st = os.stat(real)
    except OSError:
        return None
    if not stat.S_ISCHR(st.st_mode):
        return None
    pty = is_pty(st.st_rdev)
    use = device_use(real, st)
    peer = tuple(describe(p) for p in sorted(use.pty_peer))
    ident = PortIdentity(real, st.st_rdev, pty, peer)
    where = _where(url, real)
    me = os.getpid()
    if not pty:
        pid = uucp_lock.holder(real)
        if pid is not None:
            raise _locked(where, uucp_lock.lock_path(real), pid)
    # A process serving its own pty (the fake tracker, socat) may hold it as its terminal and open: that is
    # the tracker end, not someone in the way.
    terminal = sorted(use.terminal_of - use.pty_peer)
    if terminal:
        whose = "this program's own terminal" if terminal == [me] else f"the terminal of {_named(terminal)}"
        raise PortChanged(f"{where} is {whose}, not a tracker line{_stale_hint(url, pty)}; nothing was written to "
                          f"it — give the tracker's device (a fake tracker prints its path when it starts)")
    if pty and os.path.islink(path):
        _check_link_age(url, real, st, peer)
    if expected is not None:
        _check_same(url, where, ident, expected)
    others = sorted((use.open_by | use.locked_by) - use.pty_peer - {me})
    if others:
        raise PortBusy(f"{where} is in use by {_named(others)} — stop that program, or give this one another port")
    return ident


def busy_error(url: str, ident: PortIdentity, reason: str) -> PortBusy:
    """The PortBusy for an exclusive open that failed (flock or TIOCEXCL refused): who holds it, if /proc
    can tell."""
    where = _where(url, ident.device)
    try:
        st = os.stat(ident.device)
    except OSError:
        st = None
    holders = []
    if st is not None:
        use = device_use(ident.device, st)
        holders = sorted((use.locked_by | use.open_by) - use.pty_peer - {os.getpid()})
        if not holders and use.locked_by - {os.getpid()}:
            holders = sorted(use.locked_by - {os.getpid()})
    if holders:
        return PortBusy(f"{where} is in use by {_named(holders)} — stop that program, or give this one another port")
    if st is not None and os.getpid() in use.locked_by:
        return PortBusy(f"{where} is already open in this program ({describe(os.getpid())}): one reader per port")
    return PortBusy(f"{where} is held exclusively by another program ({reason}; /proc does not show which: another "
                    f"user's, or one that ended without releasing a pty) — free the port, or give this one another")


def _check_link_age(url: str, real: str, st: os.stat_result, peer: tuple[Process, ...]) -> None:
    try:
        made = os.lstat(url).st_mtime
    except OSError:
        return
    if st.st_ctime > made + STALE_LINK_MARGIN_S:
        served = f", served by {_listed(peer)}" if peer else ""
        raise PortChanged(f"{url} is a stale link: it was made {st.st_ctime - made:.0f} s before the pty it leads to "
                          f"({real}{served}), so the program that made it has stopped and its pty number was reused; "
                          f"nothing was written to it — restart the fake tracker (or whatever serves the pty) and "
                          f"use the path it prints")


def _check_same(url: str, where: str, now: PortIdentity, was: PortIdentity) -> None:
    if now.pty != was.pty:
        kinds = ("a pty", "a serial device")
        raise PortChanged(f"{url} now leads to {now.device}, {kinds[not now.pty]}, where it led to {was.device}, "
                          f"{kinds[not was.pty]}; nothing was written to it — check the device, then restart")
    if now.pty and was.peer and now.peer and not (now.peer_pids & was.peer_pids):
        raise PortChanged(f"{where} is now served by {_listed(now.peer)}, not by {_listed(was.peer)}, which served "
                          f"the tracker: the link is stale or was pointed elsewhere, and nothing was written to it — "
                          f"restart the fake tracker (or whatever serves the pty) and this program")


def _stale_hint(url: str, pty: bool) -> str:
    if pty and os.path.islink(url):
        return " (the link is stale: left by a program that stopped, its pty number reused)"
    return ""


def _named(pids: list[int]) -> str:
    return _listed(tuple(describe(p) for p in pids))


def _listed(procs: tuple[Process, ...]) -> str:
    shown = [str(p) for p in procs[:2]]
    if len(procs) > 2:
        shown.append(f"{len(procs) - 2} more")
    return " and ".join(shown) if len(shown) <= 2 else ", ".join(shown[:-1]) + " and " + shown[-1]


def uucp_lock_for(url: str, ident: PortIdentity | None):
    """Take the UUCP lock file of a real serial device (not a pty: the convention is for hardware ports);
    its path, or None (no device, a pty, or a lock folder this user cannot write)."""
    if ident is None or ident.pty:
        return None
    try:
        return uucp_lock.acquire(ident.device)
    except uucp_lock.LockHeld as held:
        raise _locked(_where(url, ident.device), held.path, held.pid) from None


def _locked(where: str, path, pid: int) -> PortBusy:
    return PortBusy(f"{where} is locked by {_named([pid])} (lock file {path}) — stop that program, or give this one "
                    f"another port")


def _where(url: str, device: str) -> str:
    """The port as given, and the device it leads to when that is another path."""
    return url if device == url else f"{url} (→ {device})"
