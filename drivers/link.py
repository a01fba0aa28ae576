"""Commands and replies over the serial ports of a Flock of Birds: open, reset, examine/change, set up.

`FlockLink` is one pyserial port (`serial.serial_for_url`: a device path, a pty, socket://, rfc2217://,
and sim:// once the program has imported flockcal.simulator); `configure_flock` runs the initialisation
sequence over one port (group mode) or one port per bird and returns the `FlockSetup` for decoding.
"""

from __future__ import annotations

import errno
import fcntl
import logging
import os
import termios
import time
from dataclasses import asdict, dataclass, field
from typing import Callable

import serial

from flockcal.drivers.commands import ADDRESSING_MODES, MAX_ADDRESS, Command, fbb_prefix
from flockcal.drivers.hemispheres import HEMISPHERES, hemisphere_bytes
from flockcal.drivers import uucp_lock
from flockcal.drivers.port_guard import PortIdentity, busy_error, check_port, uucp_lock_for
from flockcal.drivers.parameters import (
    change_command, examine_command, examine_reply_length, measurement_rate_from_word, measurement_rate_word,
    software_revision,
)
from flockcal.drivers.records import FORMATS, record_length
from flockcal.drivers.status import ERROR_CODES, BirdStatus, decode_flock_status, decode_status_word, error_is_fatal
from flockcal.drivers.words import pack_words, unpack_words
from flockcal.clock import SYSTEM
from flockcal.drivers.errors import TrackerError

log = logging.getLogger(__name__)

BAUD_RATES = (2400, 4800, 9600, 19200, 38400, 57600, 115200)
# Formats that carry position and a full orientation, most informative first (matrix before quaternion:
# the matrix needs no sign convention; the quaternion is the compact fallback the issue asks for).
FULL_FORMATS = ("position_matrix", "position_quaternion", "position_angles")
LINK_MARGIN = 0.9  # keep 10 % of the line free for jitter and command traffic


@dataclass
class Timing:
    """Delays of the initialisation sequence, in seconds (defaults: the manual's, protocol.md §1)."""

    reset_hold: float = 1.0  # RTS high (bird held in reset)
    reset_settle: float = 2.0  # after RTS drops, before the bird listens
    autoconfig: float = 0.6  # before and after FBB AUTO-CONFIG (manual: ≥ 600 ms)
    reply: float = 0.5  # longest wait for an EXAMINE reply
    drain_quiet: float = 0.05  # a drained line is quiet this long
    drain_max: float = 0.5  # give up draining a line that keeps talking

    @staticmethod
    def fast() -> "Timing":
        """Short delays for simulators, which need no settling time."""
        return Timing(reset_hold=0.0, reset_settle=0.0, autoconfig=0.05, reply=0.5,
                      drain_quiet=0.03, drain_max=0.3)


Recorder = Callable[[bytes, int, float, bytes], None]  # (kind, port index, monotonic time, bytes)


class FlockLink:
    """One serial port to a bird: raw 8N1 binary, RTS low (RTS high holds the bird in reset)."""

    def __init__(self, url: str, *, baud: int = 115200, index: int = 0, timing: Timing | None = None,
                 recorder: Recorder | None = None, read_timeout: float = 0.05):
        self.url = url
        self.baud = int(baud)
        self.index = index
        self.timing = timing or Timing()
        self.recorder = recorder
        self.read_timeout = read_timeout
        self.port: serial.SerialBase | None = None
        self.modem_lines = None  # False when the port has no RTS/DTR (a pty, some adapters)
        self.identity: PortIdentity | None = None  # the device a path led to when opened (None: a URL)
        self._lock = None  # its UUCP lock file, when this link made one

    # -- opening and closing -------------------------------------------------------------------
    def open(self, expected: PortIdentity | None = None) -> "FlockLink":
        """Open the port alone: a device path is checked first (port_guard: nobody else holds it, it is
        nobody's terminal, and with `expected` it still leads to what streamed before), its UUCP lock file
        taken, and the device node it led to opened exclusively (flock, then TIOCEXCL), so nothing is written
        to a port that turned into something else. PortBusy / PortChanged / TrackerError otherwise."""
        ident = check_port(self.url, expected)
        lock = uucp_lock_for(self.url, ident)
        try:
            port = serial.serial_for_url(
                ident.device if ident else self.url, do_not_open=True, baudrate=self.baud, bytesize=8, parity="N",
                stopbits=1, timeout=self.read_timeout, write_timeout=2.0, xonxoff=False, rtscts=False,
                dsrdtr=False, **({"exclusive": True} if ident else {}))
            # pyserial asserts RTS on open by default, which holds a bird in standby; DTR low would
            # silence it (protocol.md §11.1).
            port.rts = False
            port.dtr = True
            port.open()
        except (serial.SerialException, OSError, ValueError) as exc:
            if lock is not None:
                uucp_lock.release(lock)
            reason = getattr(exc, "strerror", None) or str(exc)
            if ident is not None and getattr(exc, "errno", None) in (errno.EAGAIN, errno.EBUSY):
                raise busy_error(self.url, ident, "locked" if exc.errno == errno.EAGAIN else "busy") from None
            raise TrackerError(f"cannot open {self.url}: {reason} — check the device name, the cable, and that "
                               f"no other program holds the port") from None
        if ident is not None:
            try:  # other openers get EBUSY (root excepted), whether or not they flock
                fcntl.ioctl(port.fileno(), termios.TIOCEXCL)
            except OSError:
                pass
        self.port, self.identity, self._lock = port, ident, lock
        return self

    def close(self) -> None:
        port, self.port = self.port, None
        lock, self._lock = self._lock, None
        if port is not None:
            if self.identity is not None:
                try:  # a pty keeps the flag after the last close while its other end is open
                    fcntl.ioctl(port.fileno(), termios.TIOCNXCL)
                except (OSError, ValueError, serial.SerialException):
                    pass
            try:
                port.close()
            except (serial.SerialException, OSError):
                pass
        if lock is not None:
            uucp_lock.release(lock)

    @property
    def is_open(self) -> bool:
        return self.port is not None and self.port.is_open

    # -- raw bytes -----------------------------------------------------------------------------
    def write(self, data: bytes) -> None:
        if self.recorder:
            self.recorder(b"W", self.index, time.monotonic(), bytes(data))
        try:
            self.port.write(data)
            self.port.flush()
        except (serial.SerialException, OSError) as exc:
            raise LinkLost(f"writing to {self.url} failed: {exc}") from None

    def read_some(self, record: bool = True) -> tuple[float, bytes]:
        """Whatever has arrived (waiting up to the read timeout for the first byte), with its arrival time.

        `record=False` leaves logging to the caller (the reader records chunks in the order it decodes them).
        """
        try:
            data = self.port.read(max(1, self.port.in_waiting))
        except (serial.SerialException, OSError, TypeError, AttributeError) as exc:
            raise LinkLost(f"reading {self.url} failed: {exc}") from None
        t = time.monotonic()
        if data and record and self.recorder:
            self.recorder(b"R", self.index, t, data)
        return t, data

    def fileno(self) -> int | None:
        """The OS file descriptor when the port has one (device paths and ptys; not sim://)."""
        try:
            return self.port.fileno()
        except (AttributeError, NotImplementedError, serial.SerialException, OSError):
            return None

    def read_available(self) -> bytes:
        """The bytes waiting now, without blocking, once select() said the port is readable; LinkLost
        if it is readable but gone (a vanished pty or USB device reads as end-of-file or EIO)."""
        # One os.read on pyserial's non-blocking descriptor: at hundreds of reads a second, pyserial's
        # read (a select, an in_waiting ioctl and timeout bookkeeping per call) cost more than the decoding.
        try:
            data = os.read(self.port.fileno(), 65536)
        except BlockingIOError:
            return b""
        except (serial.SerialException, OSError, TypeError, AttributeError) as exc:
            raise LinkLost(f"reading {self.url} failed: {exc}") from None
        if not data:
            raise LinkLost(f"reading {self.url} failed: the device reports data but returned none "
                           f"(disconnected or in use by another program)")
        return data

    def read_exact(self, n: int, timeout: float) -> bytes:
        """Up to `n` bytes, waiting at most `timeout` seconds in all."""
        out = bytearray()
        deadline = time.monotonic() + timeout
        while len(out) < n and time.monotonic() < deadline:
            try:
                chunk = self.port.read(n - len(out))
            except (serial.SerialException, OSError) as exc:
                raise LinkLost(f"reading {self.url} failed: {exc}") from None
            if chunk:
                if self.recorder:
                    self.recorder(b"R", self.index, time.monotonic(), chunk)
                out += chunk
        return bytes(out)

    def drain(self) -> int:
        """Read and discard until the line is quiet (records in flight still arrive after a stop)."""
        quiet, limit = self.timing.drain_quiet, self.timing.drain_max
        start = last = time.monotonic()
        n = 0
        while True:
            now = time.monotonic()
            if now - last >= quiet or now - start >= limit:
                break
            _, data = self.read_some()
            if data:
                n += len(data)
                last = time.monotonic()
        try:
            self.port.reset_input_buffer()
        except (serial.SerialException, OSError):
            pass
        return n

    # -- commands ------------------------------------------------------------------------------
    def reset(self) -> bool:
        """Hardware reset by RTS when the port has modem lines; True if it could be done.

        On a pty (and some USB adapters) the modem-line ioctls fail (protocol.md §11.2): the reset
        is then skipped, and the caller's STREAM STOP and drain bring the bird to a known state.
        """
        try:
            self.port.rts = True
            SYSTEM.sleep(self.timing.reset_hold)
            self.port.rts = False
            self.modem_lines = True
        except (OSError, serial.SerialException, ValueError):
            self.modem_lines = False
            log.debug("%s: no modem lines (RTS reset skipped)", self.url)
            return False
        SYSTEM.sleep(self.timing.reset_settle)
        return True

    def command(self, data: bytes, address: int = 0, addressing: str = "normal") -> None:
        """Send one command (with its data bytes), routed to FBB `address` when it is not 0."""
        self.write(fbb_prefix(address, addressing) + bytes(data))

    def examine(self, param: int, address: int = 0, addressing: str = "normal") -> bytes:
        """EXAMINE VALUE `param`: the reply bytes; LinkTimeout if fewer than expected arrive."""
        n = examine_reply_length(param, addressing)
        self.command(examine_command(param), address, addressing)
        reply = self.read_exact(n, self.timing.reply)
        if len(reply) < n:
            raise LinkTimeout(param, address, reply, n)
        return reply

    def change(self, param: int, data: bytes | int, address: int = 0, addressing: str = "normal") -> None:
        self.command(change_command(param, data), address, addressing)


class LinkLost(TrackerError):
    """The port failed (unplugged, closed by the other end)."""


class LinkTimeout(TrackerError):
    """An EXAMINE reply did not arrive in full."""

    def __init__(self, param: int, address: int, got: bytes, expected: int):
        self.param, self.address, self.got, self.expected = param, address, got, expected
        super().__init__(f"EXAMINE {param} to address {address}: {len(got)} of {expected} bytes")


# ---------------------------------------------------------------------------------------------
# Choosing the record format for the line's capacity


def link_capacity(baud: int) -> float:
    """Bytes per second an 8N1 line carries (10 bits per byte)."""
    return baud / 10.0


def record_bytes_per_second(fmt: str, *, birds_on_port: int, rate_hz: float, group: bool) -> float:
    return birds_on_port * rate_hz * record_length(fmt, group=group)


def choose_format(requested: str, *, birds_on_port: int, rate_hz: float, baud: int,
                  group: bool) -> tuple[str, list[str]]:
    """The record format to stream, and notes for the log when it is a fallback or the line is overloaded.

    "auto" takes position/matrix when the line carries it at this rate, else the most compact format
    with full orientation (position/quaternion).
    """
    cap = link_capacity(baud) * LINK_MARGIN
    need = lambda f: record_bytes_per_second(f, birds_on_port=birds_on_port, rate_hz=rate_hz, group=group)  # noqa: E731
    notes: list[str] = []
    if requested == "auto":
        fmt = "position_matrix"
        if need(fmt) > cap:
            fmt = "position_quaternion"
            notes.append(
                f"format_fallback: position/matrix needs {need('position_matrix'):.0f} B/s for {birds_on_port} "
                f"bird(s) at {rate_hz:g} Hz but {baud} baud carries about {cap:.0f} B/s; streaming "
                f"position/quaternion ({need(fmt):.0f} B/s) instead")
    else:
        if requested not in FORMATS:
            raise TrackerError(f"unknown record format {requested!r}; choose auto or one of {', '.join(FORMATS)}")
        fmt = requested
    if need(fmt) > cap:
        notes.append(
            f"link_overload: {fmt} for {birds_on_port} bird(s) at {rate_hz:g} Hz needs {need(fmt):.0f} B/s but "
            f"{baud} baud carries about {cap:.0f} B/s — records will be lost; lower --rate, raise the baud "
            f"rate, or use one port per bird")
    return fmt, notes


# ---------------------------------------------------------------------------------------------
# The initialisation sequence


@dataclass
class FlockSetup:
    """How the flock was set up: everything needed to decode its stream (stored in recordings)."""

    urls: list[str]
    birds: int
    addresses: list[int]  # FBB address of each bird (frame index i → addresses[i])
    group: bool
    mode: str  # "stream" | "point"
    record_format: str
    scale_inches: float
    rate_hz: float  # measurement rate (frames per second in stream mode)
    hemisphere: str
    baud: int
    software_revision: float = 0.0
    addressing: str = "normal"
    notes: list[str] = field(default_factory=list)
    model: str = ""  # the master's model ID (EXAMINE p15), e.g. "6DFOB"
    scale_from_tracker: bool = False  # the position scale was the tracker's own, not one asked for

    def to_dict(self) -> dict:
        return asdict(self)

    @staticmethod
    def from_dict(d: dict) -> "FlockSetup":
        known = set(FlockSetup.__dataclass_fields__)
        return FlockSetup(**{k: v for k, v in d.items() if k in known})


Emit = Callable[..., None]  # emit(kind, message, **data)


def _no_answer(link: FlockLink, got: bytes) -> TrackerError:
    if got:
        return TrackerError(
            f"garbled answer from the flock on {link.url} at {link.baud} baud (got {got.hex(' ')}) — the baud "
            f"rate probably does not match the unit's DIP switches; set --baud to match them")
    return TrackerError(
        f"no answer from the flock on {link.url} at {link.baud} baud — check the baud DIP switches, that the "
        f"unit is switched to FLY, and the cable")


def _examine(link: FlockLink, param: int, address: int = 0, addressing: str = "normal") -> bytes:
    try:
        return link.examine(param, address, addressing)
    except LinkTimeout as exc:
        if exc.got or address == 0:
            raise _no_answer(link, exc.got) from None
        raise TrackerError(f"bird at address {address} does not answer through {link.url} — check that it is "
                           f"switched to FLY and its FBB cable") from None


# Errors that do not stop a flock from measuring: reported as events, not raised.
PASSING_ERRORS = frozenset({6, 11, 28, 32})


def check_bird_errors(links: list[FlockLink], setup: "FlockSetup", emit: Emit,
                      birds: list[int] | None = None) -> list[tuple[int, int]]:
    """Read the birds' error registers (cleared by reading); emit bird_error for each, raise TrackerError
    on one that stops measuring. Returns (bird index, code) for the birds that reported an error.

    The expanded error code (p16) also names the address concerned (the unresponsive slave for error
    13), so an error the master holds for another bird is blamed on that bird.
    """
    found = []
    fatal = None
    for i in (range(setup.birds) if birds is None else birds):
        link, addr = _route(links, setup, i)
        reply = _examine(link, 16, addr, setup.addressing)
        code, about = reply[0], reply[1] & 0x7F
        if code == 0:
            continue
        j = setup.addresses.index(about) if about in setup.addresses else i
        address = setup.addresses[j]
        name = ERROR_CODES.get(code, "unknown error code")
        message = f"bird {j} (address {address}) reports error {code}: {name}{error_hint(code)}"
        found.append((j, code))
        emit("bird_error", message, bird=j, address=address, code=int(code), name=name)
        if code not in PASSING_ERRORS and fatal is None:
            fatal = message
    if fatal:
        raise TrackerError(fatal)
    return found


def error_hint(code: int) -> str:
    hints = {
        31: " — lower --rate",
        32: " — move the sensor further from the transmitter",
        29: " — check the transmitter cable and that the transmitter's unit is running",
        30: " — attach the extended range transmitter or configure without it",
        9: " — the flock was not auto-configured; check that --birds matches the units switched to FLY",
        8: " — no birds accessible: switch the units to FLY and check the FBB cables",
        13: " — a slave did not answer: check its FLY switch and FBB cable",
        11: " — serial overrun or framing error: check the baud rate and the cable",
        18: " — illegal baud rate: check the DIP switches",
    }
    if code in hints:
        return hints[code]
    if error_is_fatal(code):
        return " — power-cycle the unit; if it persists, the unit needs service"
    return ""


def _route(links: list[FlockLink], setup: "FlockSetup", bird: int) -> tuple[FlockLink, int]:
    """The port and FBB address prefix through which bird `bird` is addressed."""
    if setup.group or len(links) == 1:
        return links[0], (setup.addresses[bird] if setup.birds > 1 else 0)
    return links[bird], 0


@dataclass(frozen=True)
class FlockIdentity:
    """What the master says it is, read before anything is changed (EXAMINE p15, p0, p3)."""

    model: str  # model ID, space padding removed: "6DFOB", "6DERC", "PCBIRD", …
    status: BirdStatus
    scale_inches: float  # the position scale it is set to now, 36 or 72


# Model IDs that speak the Flock's RS-232 command set with sensors at addresses 1..N (its close relatives).
FLOCK_MODELS = ("6DFOB", "6DBOF", "PCBIRD", "SPACEPAD")


def identify(master: FlockLink) -> FlockIdentity:
    """Ask the master what it is: model ID (p15), bird status (p0) and position scaling (p3)."""
    model = _examine(master, 15).decode("ascii", "replace").strip(" \x00")
    status = decode_status_word(_examine(master, 0))
    scale = _examine(master, 3)
    return FlockIdentity(model=model, status=status, scale_inches=72.0 if scale[0] == 1 else 36.0)


def check_identity(ident: FlockIdentity, link: FlockLink, birds: int) -> None:
    """Refuse a unit this driver cannot read, naming what it is and the fix."""
    if ident.model == "6DERC":
        raise TrackerError(f"the unit on {link.url} is an extended range controller (model 6DERC): flockcal reads "
                           f"standard Flock transmitters only — connect to a Flock of Birds master instead")
    if birds > 1 and not ident.status.master:
        raise TrackerError(f"the unit on {link.url} says it is not the flock's master (bird status, EXAMINE 0) — "
                           f"connect the cable to the master (FBB address 1) or read it with --birds 1")


def configure_flock(links: list[FlockLink], *, birds: int, rate_hz: float | None, record_format: str,
                    group: bool, mode: str, hemisphere: str, scale_inches: float | None,
                    emit: Emit) -> FlockSetup:
    """Reset and initialise the flock; returns how it was set up. Raises TrackerError on any problem.

    Sequence (protocol.md §6, with the manual's delays): RTS reset where possible, STREAM STOP and
    drain; check the master answers (software revision) and ask what it is (model, status, position
    scale); FBB AUTO-CONFIG for N birds; check every bird is accessible and running (flock status);
    measurement rate; per bird: position scale, record format, hemisphere; group mode on/off; read back
    every bird's position scale; read and name any error code. `scale_inches=None` keeps the scale the
    master is set to; `rate_hz=None` keeps its measurement rate.
    """
    if hemisphere not in HEMISPHERES:
        raise TrackerError(f"unknown hemisphere {hemisphere!r}; choose one of {', '.join(HEMISPHERES)}")
    if scale_inches is not None and scale_inches not in (36, 72):
        raise TrackerError(f"position scale must be 36 or 72 inches, got {scale_inches}")
    if not group and len(links) != birds:
        raise TrackerError(f"one port per bird needs {birds} ports, got {len(links)}; give one --port per bird "
                           f"or use group mode")
    master = links[0]
    timing = master.timing
    for link in links:
        link.reset()
    for link in links:
        link.write(bytes([Command.STREAM_STOP]))
    for link in links:
        link.drain()

    raw = _examine(master, 1)
    revision = software_revision(raw)
    if not (1 <= raw[0] <= 9 and raw[1] < 100):  # a reply at the wrong baud rate is noise
        raise _no_answer(master, raw)
    addressing = "normal"
    if revision >= 3.67:
        addressing = ADDRESSING_MODES.get(_examine(master, 19)[0], "normal")
    ident = identify(master)
    check_identity(ident, master, birds)
    if ident.model not in FLOCK_MODELS:
        emit("tracker_model", f"the unit on {master.url} reports model {ident.model!r}, not a Flock of Birds model "
                              f"({', '.join(FLOCK_MODELS)}); reading it with the Flock's commands")
    if ident.status.sleeping:  # SLEEP keeps the transmitter off: the data would never change
        master.write(bytes([Command.RUN]))
    from_tracker = scale_inches is None
    if from_tracker:
        scale_inches = ident.scale_inches
    limit = MAX_ADDRESS[addressing]
    if birds > limit:
        raise TrackerError(f"{birds} birds need more than the {limit} addresses of {addressing} addressing — set "
                           f"the addressing-mode DIP switches (expanded: 30, super-expanded: 126)")

    addresses = list(range(1, birds + 1))
    if birds > 1:
        SYSTEM.sleep(timing.autoconfig)
        master.change(50, birds)
        SYSTEM.sleep(timing.autoconfig)
        status = decode_flock_status(_examine(master, 36, 0, addressing))
        for i, a in enumerate(addresses):
            if not status.accessible[a - 1]:
                raise TrackerError(f"bird {i} (address {a}) is not accessible after auto-configuration — switch "
                                   f"it to FLY and check its FBB cable, or lower --birds")
            if not status.running[a - 1]:
                raise TrackerError(f"bird {i} (address {a}) is not running after auto-configuration — check it "
                                   f"is switched to FLY, then retry")
            if not status.sensor[a - 1]:
                raise TrackerError(f"bird {i} (address {a}) has no sensor attached — plug in its sensor or lower "
                                   f"--birds")

    setup = FlockSetup(urls=[l.url for l in links], birds=birds, addresses=addresses, group=bool(group),
                       mode=mode, record_format="", scale_inches=float(scale_inches), rate_hz=0.0,
                       hemisphere=hemisphere, baud=master.baud, software_revision=revision,
                       addressing=addressing, model=ident.model, scale_from_tracker=from_tracker)
    if birds == 1:
        setup.group = False

    if rate_hz:
        if not 1.0 <= rate_hz <= 180.0:
            raise TrackerError(f"a Flock of Birds measures at up to about 144 Hz (180 at most); got --rate {rate_hz:g}")
        for link in (links if not setup.group else [master]):
            link.change(7, measurement_rate_word(rate_hz))
    word = int(unpack_words(_examine(master, 7), signed=False)[0])
    setup.rate_hz = measurement_rate_from_word(word) if word else (rate_hz or 103.3)

    fmt, notes = choose_format(record_format, birds_on_port=birds if setup.group else 1, rate_hz=setup.rate_hz,
                               baud=master.baud, group=setup.group)
    setup.record_format = fmt
    setup.notes = notes
    for note in notes:
        kind, _, text = note.partition(": ")
        emit(kind, text)

    scale = 1 if scale_inches == 72 else 0
    hemi = hemisphere_bytes(hemisphere)
    for i in range(birds):
        link, addr = _route(links, setup, i)
        link.change(3, pack_words([scale]), addr, addressing)
        link.command(bytes([FORMATS[fmt].command]), addr, addressing)
        link.command(bytes([Command.HEMISPHERE]) + hemi, addr, addressing)
    if birds > 1:
        master.change(35, 1 if setup.group else 0)
    for link in links:
        link.drain()
    check_position_scale(links, setup)
    check_bird_errors(links, setup, emit)
    return setup


def check_position_scale(links: list[FlockLink], setup: FlockSetup) -> None:
    """Read back every bird's position scale (EXAMINE p3): positions are decoded at `setup.scale_inches`,
    so a bird left at the other scale would report every position off by a factor of two."""
    want = 1 if setup.scale_inches == 72 else 0
    for i in range(setup.birds):
        link, addr = _route(links, setup, i)
        got = _examine(link, 3, addr, setup.addressing)
        if got[0] != want:
            has = {0: "36-inch", 1: "72-inch"}.get(got[0], f"unknown ({got[0]})")
            raise TrackerError(f"bird {i} (address {setup.addresses[i]}) kept the {has} position scale after being "
                               f"set to {setup.scale_inches:g} in — check that it is not behind an extended range "
                               f"controller, or power-cycle it")


def start_stream(links: list[FlockLink], setup: FlockSetup) -> None:
    """STREAM: to the master in group mode, to every port with one port per bird."""
    for link in (links[:1] if setup.group or len(links) == 1 else links):
        link.write(bytes([Command.STREAM]))


def poll(links: list[FlockLink], setup: FlockSetup) -> None:
    """POINT: one record per bird (one group response in group mode)."""
    for link in (links[:1] if setup.group or len(links) == 1 else links):
        link.write(bytes([Command.POINT]))


def stop_stream(links: list[FlockLink]) -> None:
    """STREAM STOP on every port that still works (records in flight are left to the caller's drain)."""
    for link in links:
        if link.is_open:
            try:
                link.write(bytes([Command.STREAM_STOP]))
            except TrackerError:
                pass
