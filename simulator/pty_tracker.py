"""Serve a FakeFlock on real pseudo-terminals, so any serial client (pyserial, VRPN) can talk to it.

Each port is a pty whose slave is put in raw mode at once and kept open by us; `.device` is a stable
symlink to the slave, re-pointed to a fresh pty by `reconnect()` (a pty path cannot be reopened).
"""

from __future__ import annotations

import errno
import os
import select
import shutil
import tempfile
import termios
import threading
import tty

from flockcal.simulator.fake_tracker import FakeFlock, FakeTrackerError, LineFaults, PoseSource

# termios speed constants → baud, to follow the speed the client sets when baud=None.
_SPEEDS = {getattr(termios, f"B{b}"): b for b in (
    1200, 2400, 4800, 9600, 19200, 38400, 57600, 115200, 230400, 460800, 500000, 921600)
    if hasattr(termios, f"B{b}")}


class _Pty:
    def __init__(self) -> None:
        self.master, self.slave = os.openpty()
        # Raw at once: otherwise the slave echoes our own output back to us as commands.
        tty.setraw(self.slave, termios.TCSANOW)
        os.set_blocking(self.master, False)
        self.path = os.ttyname(self.slave)
        self.backlog = bytearray()

    def close(self) -> None:
        for fd in (self.master, self.slave):
            try:
                os.close(fd)
            except OSError:
                pass


class PtyTracker(LineFaults):
    """A fake flock behind one pty per port, served by a background thread.

    source: a PoseSource (ignored when `flock` is given). baud: line speed to emulate (ptys
    themselves ignore baud); None follows whatever speed the client sets on the port.
    Other keywords go to FakeFlock (rate_hz, ert, clock, …).
    """

    def __init__(self, source: PoseSource | None = None, *, birds: int | None = None,
                 baud: float | None = 115200, ports: int = 1, flock: FakeFlock | None = None,
                 poll_interval: float = 0.002, link_dir: str | None = None, **flock_kwargs) -> None:
        if flock is None:
            if source is None:
                raise FakeTrackerError("PtyTracker needs a pose source or a FakeFlock")
            n = source.n_sensors if birds is None else birds
            flock = FakeFlock(source, birds=n, baud=baud or 115200,
                              ports=n if ports > 1 else 1, **flock_kwargs)
        self.flock = flock
        self.follow_client_baud = baud is None
        self.poll_interval = float(poll_interval)
        self._own_dir = link_dir is None
        self.link_dir = link_dir or tempfile.mkdtemp(prefix="flockcal-fob-")
        self._ptys: list[_Pty | None] = [None] * flock.n_ports
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._last_speed: list[int | None] = [None] * flock.n_ports

    # ------------------------------------------------------------------ lifecycle

    def start(self) -> "PtyTracker":
        for k in range(self.flock.n_ports):
            self._open(k)
        self._stop.clear()
        self._thread = threading.Thread(target=self._serve, name="fake-flock-pty", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        with self._lock:
            for k, p in enumerate(self._ptys):
                if p is not None:
                    p.close()
                    self._ptys[k] = None
        if self._own_dir:
            shutil.rmtree(self.link_dir, ignore_errors=True)

    def __enter__(self) -> "PtyTracker":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    @property
    def devices(self) -> list[str]:
        """Stable paths (symlinks to the current pty slaves), one per port."""
        return [os.path.join(self.link_dir, f"fob{k}") for k in range(self.flock.n_ports)]

    @property
    def device(self) -> str:
        return self.devices[0]

    def pending(self, port: int | None = None) -> int:
        """Bytes the flock has sent by its clock's present that have not yet reached the pty (all ports by
        default): 0 once the server thread has handed on everything a client could read now."""
        with self._lock:
            return sum(self.flock.in_waiting(k) + len(p.backlog) for k in self._ports(port)
                       if (p := self._ptys[k]) is not None)

    @property
    def pts_paths(self) -> list[str | None]:
        """The /dev/pts/N behind each port (changes on reconnect)."""
        return [p.path if p else None for p in self._ptys]

    # ------------------------------------------------------------------ faults

    def disconnect(self, port: int | None = None) -> None:
        """Unplug: close the pty (the client gets EIO / hang-up) and remove the device path."""
        for k in self._ports(port):
            with self._lock:
                p, self._ptys[k] = self._ptys[k], None
                if p is not None:
                    p.close()
                try:
                    os.unlink(self.devices[k])
                except FileNotFoundError:
                    pass
            self.flock.disconnect(k)

    def reconnect(self, port: int | None = None) -> None:
        """Plug back in: a new pty behind the same device path; the client must reopen it."""
        for k in self._ports(port):
            if self._ptys[k] is None:
                self._open(k)
            self.flock.reconnect(k)


    # ------------------------------------------------------------------ internals

    def _ports(self, port: int | None) -> range:
        return range(self.flock.n_ports) if port is None else range(port, port + 1)

    def _open(self, k: int) -> None:
        p = _Pty()
        link = self.devices[k]
        tmp = link + ".new"
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        os.symlink(p.path, tmp)
        os.replace(tmp, link)  # atomic re-point
        with self._lock:
            self._ptys[k] = p
        self._last_speed[k] = None

    def _serve(self) -> None:
        while not self._stop.is_set():
            with self._lock:
                live = [(k, p) for k, p in enumerate(self._ptys) if p is not None]
            fds = {p.master: (k, p) for k, p in live}
            try:
                readable, _, _ = select.select(list(fds), [], [], self.poll_interval)
            except (OSError, ValueError):
                continue  # a pty closed under us by disconnect(); next round
            # I/O under the lock, re-checking each pty: disconnect() may have closed it (and
            # its fd number may already belong to someone else).
            with self._lock:
                for fd in readable:
                    k, p = fds[fd]
                    if self._ptys[k] is not p:
                        continue
                    try:
                        data = os.read(fd, 4096)
                    except OSError:
                        continue
                    if data:
                        self.flock.write(data, k)
                if self.follow_client_baud:
                    self._follow_baud(live)
                for k, p in live:
                    if self._ptys[k] is p:
                        self._pump(k, p)
            if not fds:
                self._stop.wait(self.poll_interval)

    def _pump(self, k: int, p: _Pty) -> None:
        p.backlog += self.flock.read(k)
        if not p.backlog:
            return
        try:
            n = os.write(p.master, p.backlog)
        except BlockingIOError:
            n = 0
        except OSError as e:
            if e.errno not in (errno.EIO, errno.EBADF):
                raise
            n = 0
        del p.backlog[:n]
        # A client that does not read loses the oldest bytes, as with an overrun serial port.
        excess = len(p.backlog) - self.flock.buffer_limit
        if excess > 0:
            del p.backlog[:excess]

    def _follow_baud(self, live) -> None:
        for k, p in live:
            try:
                speed = termios.tcgetattr(p.slave)[5]
            except termios.error:
                continue
            if speed != self._last_speed[k] and speed in _SPEEDS:
                self._last_speed[k] = speed
                self.flock.set_baud(_SPEEDS[speed], k)
