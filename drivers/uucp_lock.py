"""The UUCP lock file of a serial device: /var/lock/LCK..ttyUSB0 holding its owner's PID in ASCII, the
convention minicom, cu, gpsd and ModemManager's neighbours honour. Stale locks (a PID that is gone) are
removed; where the lock folder cannot be written, the port is opened without one (and a warning says so).
"""

from __future__ import annotations

import errno
import logging
import os
from pathlib import Path

from flockcal.drivers.port_holders import alive

log = logging.getLogger(__name__)

LOCK_DIR = "/var/lock"  # Debian and most others: a link to /run/lock, mode 1777
LOCK_DIR_VARIABLE = "FLOCKCAL_LOCK_DIR"  # another folder (tests, systems that use /var/spool/lock)

_held: set[str] = set()  # lock files this process holds: a second opener in the same process is refused too
_warned: set[str] = set()


def lock_dir() -> Path:
    return Path(os.environ.get(LOCK_DIR_VARIABLE) or LOCK_DIR)


def lock_path(device: str) -> Path:
    """The lock file of the device node `device` (its real path): LCK..<name>."""
    return lock_dir() / f"LCK..{os.path.basename(device)}"


def read_pid(path: Path) -> int | None:
    """The PID in a lock file (HDB ASCII, or the old 4-byte binary form); None if it holds none."""
    try:
        data = path.read_bytes()
    except OSError:
        return None
    text = data.strip()
    if text.isdigit():
        return int(text)
    if len(data) == 4:
        return int.from_bytes(data, "little")
    return None


def holder(device: str) -> int | None:
    """The live process holding `device`'s lock file (this process when it holds it), else None."""
    path = lock_path(device)
    pid = read_pid(path)
    if pid is None or not alive(pid):
        return None
    if pid == os.getpid() and str(path) not in _held:
        return None  # our own PID left by nothing we hold: stale
    return pid


class LockHeld(Exception):
    """Another live process holds the lock file."""

    def __init__(self, path: Path, pid: int):
        super().__init__(f"{path} is held by PID {pid}")
        self.path, self.pid = path, pid


def acquire(device: str) -> Path | None:
    """Create `device`'s lock file holding this PID and return its path; None when the lock folder cannot
    be written (the port is then held by flock and TIOCEXCL alone, said once per device in the log).
    LockHeld when a live process holds it; a stale one (its process gone) is removed first."""
    path = lock_path(device)
    pid = os.getpid()
    tmp = path.with_name(f"LTMP.{pid}")
    try:
        tmp.write_bytes(f"{pid:10d}\n".encode("ascii"))
    except OSError as exc:
        other = holder(device)  # an unwritable folder can still hold another program's lock
        if other is not None:
            raise LockHeld(path, other) from None
        _cannot_lock(path, exc)
        return None
    try:
        for _ in range(3):
            try:
                os.link(tmp, path)  # atomic: it fails if the lock exists
            except FileExistsError:
                other = holder(device)
                if other is not None:
                    raise LockHeld(path, other) from None
                try:
                    path.unlink()  # stale: its process is gone
                    log.info("removed the stale lock file %s", path)
                except FileNotFoundError:
                    pass
                continue
            except OSError as exc:
                _cannot_lock(path, exc)
                return None
            _held.add(str(path))
            return path
        raise LockHeld(path, read_pid(path) or 0)  # re-created under us three times: someone is taking it
    finally:
        try:
            tmp.unlink()
        except OSError:
            pass


def release(path: Path) -> None:
    """Remove a lock file this process made (only while it still names this process)."""
    _held.discard(str(path))
    if read_pid(path) == os.getpid():
        try:
            path.unlink()
        except OSError:
            pass


def _cannot_lock(path: Path, exc: OSError) -> None:
    if str(path) in _warned:
        return
    _warned.add(str(path))
    why = {errno.EACCES: "permission denied", errno.EPERM: "permission denied", errno.EROFS: "read-only",
           errno.ENOENT: "no such folder"}.get(exc.errno, exc.strerror or str(exc))
    log.warning("cannot create the lock file %s (%s): programs that honour UUCP lock files (minicom, cu) will not "
                "see that flockcal holds the port; flock and TIOCEXCL still keep other openers out", path, why)
