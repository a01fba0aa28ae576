"""The tracker reader: a thread that sets up a Flock of Birds, reads it, and hands out frames in batches.

It owns the serial ports (one, or one per bird), records every byte to a .fobraw file when asked (for
its whole run, or per session with start_recording/stop_recording), hands out `Frames`, survives garbage, dropped bytes, stalls and unplugged cables (reconnecting with backoff and
re-initialising the flock), and reports each of these as a `TrackerEvent`.
"""

from __future__ import annotations

import errno
import logging
import queue
import select
import threading
from dataclasses import asdict, dataclass, field, replace
from typing import Callable

import numpy as np

from flockcal import __version__
from flockcal.clock import SYSTEM, Clock
from flockcal.drivers.assembly import FrameAssembler
from flockcal.drivers.hemispheres import HEMISPHERES
from flockcal.drivers.link import (FlockLink, FlockSetup, LinkLost, Timing, TrackerError, check_bird_errors,
                                   configure_flock, poll, start_stream, stop_stream)
from flockcal.drivers.rate_check import RateCheck
from flockcal.drivers.recording import RecordingWriter
from flockcal.drivers.records import FORMATS, record_length
from flockcal.drivers.tracker_status import TrackerStatus
from flockcal.frames import Frames
from flockcal.threads import name_os_thread

log = logging.getLogger(__name__)

__all__ = ["TrackerConfig", "TrackerEvent", "TrackerReader", "TrackerError"]


@dataclass
class TrackerConfig:
    """What to read and how. The first ten fields are the public contract; the rest tune robustness."""

    urls: list[str]
    birds: int = 1
    rate_hz: float | None = None  # measurement rate to set (None: keep the flock's); the poll rate in point mode
    record_format: str = "auto"  # "auto" or a FORMATS name
    group: bool | None = None  # None: group mode with one URL, one port per bird with one URL per bird
    hemisphere: str = "forward"
    scale_inches: int | None = 36  # 36 or 72; None keeps the scale the tracker is set to
    baud: int = 115200
    mode: str = "stream"  # "stream" | "point"
    recording_path: str | None = None
    timing: Timing | None = None  # None: the manual's delays, or short ones when every URL is sim://
    stall_timeout: float = 1.0  # seconds without a byte on a port before the line counts as stalled
    batch_interval: float = 0.02  # seconds between on_frames calls
    backoff: tuple[float, float] = (0.25, 5.0)  # first and longest wait between reconnection attempts
    max_reconnects: int | None = None  # give up after this many failed attempts in a row (None: never)
    hemisphere_tracking: bool = True
    max_speed: float = 20.0  # m/s: a record next to lost bytes that implies more is treated as garbled
    max_turn_rate: float = 60.0  # rad/s, likewise for orientation
    tracker_words: bool = False  # frames carry the data words they were decoded from (Frames.words)

    def __post_init__(self) -> None:
        if isinstance(self.urls, str):
            self.urls = [self.urls]
        self.urls = [str(u) for u in self.urls]

    def resolved_group(self) -> bool:
        if self.group is not None:
            return bool(self.group)
        return len(self.urls) == 1

    def resolved_timing(self) -> Timing:
        if self.timing is not None:
            return self.timing
        return Timing.fast() if all(u.startswith("sim://") for u in self.urls) else Timing()

    def validate(self) -> None:
        """Raise TrackerError for settings that no flock could accept (checked before any I/O)."""
        if not self.urls:
            raise TrackerError("no tracker port given — pass --port with a device path or URL")
        if self.birds < 1:
            raise TrackerError(f"--birds must be at least 1, got {self.birds}")
        if self.mode not in ("stream", "point"):
            raise TrackerError(f"mode must be 'stream' or 'point', got {self.mode!r}")
        if self.record_format != "auto" and self.record_format not in FORMATS:
            raise TrackerError(f"unknown record format {self.record_format!r}; choose auto or one of "
                               f"{', '.join(FORMATS)}")
        if self.hemisphere not in HEMISPHERES:
            raise TrackerError(f"unknown hemisphere {self.hemisphere!r}; choose one of {', '.join(HEMISPHERES)}")
        if self.scale_inches is not None and self.scale_inches not in (36, 72):
            raise TrackerError(f"position scale must be 36 or 72 inches, got {self.scale_inches}")
        # RS-232 tops out at 115200; faster lines are the RS-485 host interface or an emulated line.
        if self.baud not in (2400, 4800, 9600, 19200, 38400, 57600, 115200, 230400, 460800, 500000, 921600):
            raise TrackerError(f"a Flock of Birds talks at 2400…115200 baud over RS-232 (up to 500000 over "
                               f"RS-485, 921600 for an emulated line); {self.baud} is not one of its rates")
        group = self.resolved_group()
        if not group and len(self.urls) != self.birds:
            raise TrackerError(f"one port per bird needs {self.birds} URLs, got {len(self.urls)}; give one --port "
                               f"per bird, or a single port for group mode")
        if group and len(self.urls) != 1:
            raise TrackerError(f"group mode reads all birds through one port, got {len(self.urls)} URLs")

    def to_dict(self) -> dict:
        d = asdict(self)
        d["timing"] = asdict(self.resolved_timing())
        return d


@dataclass(frozen=True)
class TrackerEvent:
    """Something the operator should know: connected, disconnected, stalled, reconnecting, resync,
    bird_error, format_fallback, link_overload, hemisphere_flip, position_saturated, error, stopped."""

    kind: str
    message: str
    time: float  # on the reader's clock (its monotonic seconds)
    data: dict = field(default_factory=dict)

    @property
    def code(self) -> int | None:
        return self.data.get("code")

    @property
    def name(self) -> str | None:
        return self.data.get("name")

    @property
    def bird(self) -> int | None:
        return self.data.get("bird")

    @property
    def disk_full(self) -> bool:
        """A `recording_stopped` for want of room on the disk."""
        return bool(self.data.get("disk_full"))

    def __str__(self) -> str:
        return f"{self.kind}: {self.message}"


FramesCallback = Callable[[Frames], None]
EventCallback = Callable[[TrackerEvent], None]


class _Stalled(Exception):
    """A port or some birds went quiet; `birds` are the ones to ask for an error code."""

    def __init__(self, birds: list[int]):
        super().__init__(f"stalled: birds {birds}")
        self.birds = birds


class TrackerReader:
    """Reads the tracker on a background thread and calls `on_frames(frames)` with a batch of `Frames`.

    Callbacks run on the reader thread at most every `batch_interval` (tens of ms), when there are frames
    or news: they must return quickly (keep the Frames or push them to a queue), or bytes back up in the
    serial driver. The recording methods may be called from any thread.
    """

    def __init__(self, cfg: TrackerConfig, on_frames: FramesCallback | None = None,
                 on_event: EventCallback | None = None, recording_header: dict | None = None,
                 clock: Clock = SYSTEM):
        cfg.validate()
        self.cfg = cfg
        self.clock = clock  # dates the bytes and frames; times every wait, deadline and stall
        self.recording_header = dict(recording_header or {})  # more header entries (e.g. sensor names)
        self.on_frames = on_frames
        self.on_event = on_event
        self.timing = cfg.resolved_timing()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()
        self._connected_once = threading.Event()
        self._first_failure: TrackerError | None = None
        self._links: list[FlockLink] = []
        self._identities: dict = {}  # url → PortIdentity of the device it led to when the flock first answered
        # The recording in progress: swapped under _recording_lock, read once per use by the reader thread
        # (a writer closed meanwhile ignores what it is given).
        self._recorder: RecordingWriter | None = None
        self._recording_lock = threading.Lock()
        self._stream_marker: dict | None = None  # the current stream's setup: every recording starts with it
        self.setup: FlockSetup | None = None
        self._status = TrackerStatus(birds=cfg.birds, urls=list(cfg.urls), mode=cfg.mode, group=cfg.resolved_group(),
                                     recording_path=cfg.recording_path, scale_inches=cfg.scale_inches)
        self._totals = dict(frames=0, dropped_records=0, resynced=0, rejected_records=0, dropped_bytes=0,
                            saturated_records=0)

    # -- public --------------------------------------------------------------------------------
    def start(self, wait: float | None = None) -> "TrackerReader":
        """Start the reader thread. With `wait`, block until the flock streams, raising the first
        connection error instead of retrying (what a command line wants)."""
        if self._thread is not None:
            raise TrackerError("this reader was already started; make a new TrackerReader")
        if self.cfg.recording_path:
            settings = {**self.recording_header, "flockcal": __version__, "config": self.cfg.to_dict()}
            # Pending until the flock streams: a start that fails leaves no stub behind.
            self._recorder = RecordingWriter(self.cfg.recording_path, settings, pending=True, clock=self.clock)
        self._fail_fast = wait is not None
        self._thread = threading.Thread(target=self._run, name="flockcal-tracker", daemon=True)
        self._thread.start()
        if wait is not None:
            deadline = self.clock.monotonic() + wait
            while not self.clock.wait(self._connected_once, 0.05):
                if self._first_failure is not None or not self._thread.is_alive():
                    self.stop()
                    raise self._first_failure or TrackerError("the tracker reader stopped before connecting")
                if self.clock.monotonic() > deadline:
                    self.stop()
                    raise TrackerError(f"the flock on {', '.join(self.cfg.urls)} did not start streaming within "
                                       f"{wait:g} s")
            self._fail_fast = False
        return self

    def stop(self, timeout: float = 5.0) -> None:
        """Stop streaming, deliver the last frames, close the ports and the recording."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout)
        if self._thread is None or not self._thread.is_alive():
            self.stop_recording()

    def start_recording(self, path, header: dict | None = None) -> None:
        """Record every byte from now on to a new .fobraw at `path`, ending any recording in progress.

        Its header holds `recording_header`, `header`, the software version and the configuration; it
        starts with the current stream's setup (once the flock streams), so it replays on its own.
        Raises RecordingError when the file cannot be created (nothing else changes then).
        """
        settings = {**self.recording_header, **(header or {}), "flockcal": __version__, "config": self.cfg.to_dict()}
        writer = RecordingWriter(path, settings, clock=self.clock)
        with self._recording_lock:
            if self._stream_marker is not None:
                writer.mark(self.clock.monotonic(), self._stream_marker)
            old, self._recorder = self._recorder, writer
        if old is not None:
            old.close()

    def stop_recording(self) -> None:
        """Close the recording in progress, if any; the reader reads on."""
        with self._recording_lock:
            old, self._recorder = self._recorder, None
        if old is not None:
            old.close()

    def status(self) -> TrackerStatus:
        """The link now (a copy)."""
        with self._lock:
            return replace(self._status, urls=list(self._status.urls))

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    # -- events and bookkeeping ----------------------------------------------------------------
    def _emit(self, kind: str, message: str, **data) -> None:
        event = TrackerEvent(kind, message, self.clock.monotonic(), data)
        level = logging.INFO if kind in ("connected", "resync", "hemisphere_flip", "stopped") else logging.WARNING
        log.log(level, "%s", event)
        if kind in ("disconnected", "stalled", "error", "bird_error"):
            with self._lock:
                self._status.last_error = message
                if kind == "bird_error":
                    self._status.bird_errors += 1
        if (rec := self._recorder) is not None:
            rec.mark(event.time, {"event": kind, "message": message, **data})
        if self.on_event is not None:
            try:
                self.on_event(event)
            except Exception:  # a broken listener must not stop the tracker
                log.exception("on_event callback failed")

    def _record(self, kind: bytes, port: int, t: float, data: bytes) -> None:
        if (rec := self._recorder) is not None:
            (rec.read if kind == b"R" else rec.wrote)(t, port, data)
            if rec.error is not None:
                self._recording_failed(rec)

    def _recording_failed(self, rec: RecordingWriter) -> None:
        """A write of the recording failed (a full disk): it ended there, whole up to its last flush; say
        so once, and read on."""
        with self._recording_lock:
            if self._recorder is not rec:
                return
            self._recorder = None
        exc = rec.error
        self._emit("recording_stopped", f"the raw recording {rec.path} stopped: {exc.strerror or exc}; what was "
                                        "written is kept, and the tracker is still read",
                   path=str(rec.path), errno=exc.errno, disk_full=exc.errno in (errno.ENOSPC, errno.EDQUOT))

    def _deliver(self, asm: FrameAssembler) -> None:
        for kind, message, data in asm.take_events():
            self._emit(kind, message, **data)
        frames = asm.take()
        with self._lock:
            s = self._status
            s.frames = self._totals["frames"] + asm.frames
            s.dropped_records = self._totals["dropped_records"] + asm.dropped_records
            s.resynced = self._totals["resynced"] + asm.resyncs
            s.rejected_records = self._totals["rejected_records"] + asm.rejected_records
            s.dropped_bytes = self._totals["dropped_bytes"] + asm.dropped_bytes
            s.saturated_records = self._totals["saturated_records"] + asm.saturated_records
        if (rec := self._recorder) is not None:
            rec.flush()
            if rec.error is not None:
                self._recording_failed(rec)
        if len(frames) and self.on_frames is not None:
            try:
                self.on_frames(frames)
            except Exception:
                log.exception("on_frames callback failed")

    def _retire(self, asm: FrameAssembler | None, reason: str) -> None:
        """End a session's decoding: emit what is pending, fold its counters into the totals."""
        if asm is None:
            return
        if (rec := self._recorder) is not None:
            rec.mark(self.clock.monotonic(), {"flush": True, "reason": reason})
        asm.flush()
        self._deliver(asm)
        with self._lock:
            for k, v in (("frames", asm.frames), ("dropped_records", asm.dropped_records),
                         ("resynced", asm.resyncs), ("rejected_records", asm.rejected_records),
                         ("dropped_bytes", asm.dropped_bytes), ("saturated_records", asm.saturated_records)):
                self._totals[k] += v

    # -- the thread ----------------------------------------------------------------------------
    def _run(self) -> None:
        name_os_thread("fc-tracker")
        attempt = 0
        try:
            while not self._stop.is_set():
                asm = None
                try:
                    asm = self._connect()
                    attempt = 0
                    self._session(asm)
                    self._retire(asm, "stop")
                    asm = None
                    break
                except (TrackerError, _Stalled, OSError) as exc:
                    if isinstance(exc, _Stalled):
                        self._ask_birds(exc.birds)
                    self._retire(asm, type(exc).__name__)
                    self._close_links()
                    with self._lock:
                        self._status.connected = False
                    if self._fail_fast and not self._connected_once.is_set():
                        # The caller of start(wait=…) raises it; no event, no retry.
                        self._first_failure = exc if isinstance(exc, TrackerError) else TrackerError(str(exc))
                        return
                    if isinstance(exc, _Stalled):
                        pass  # already reported
                    elif isinstance(exc, LinkLost) or isinstance(exc, OSError):
                        self._emit("disconnected", f"{exc} — will reconnect")
                    else:
                        self._emit("error", str(exc))
                    attempt += 1
                    if self.cfg.max_reconnects is not None and attempt > self.cfg.max_reconnects:
                        self._emit("error", f"giving up after {attempt - 1} reconnection attempts: {exc}")
                        return
                    first, longest = self.cfg.backoff
                    delay = min(longest, first * 2 ** (attempt - 1))
                    with self._lock:
                        self._status.reconnects += 1
                    self._emit("reconnecting", f"reconnecting in {delay:.2f} s (attempt {attempt})",
                               attempt=attempt, delay=delay)
                    self.clock.wait(self._stop, delay)
        finally:
            self._close_links()
            with self._lock:
                self._status.connected = False
            self.stop_recording()
            self._emit_stopped()

    def _emit_stopped(self) -> None:
        if self.on_event is not None:
            try:
                self.on_event(TrackerEvent("stopped", "the tracker reader stopped", self.clock.monotonic(), {}))
            except Exception:
                log.exception("on_event callback failed")

    def _close_links(self) -> None:
        links, self._links = self._links, []
        for link in links:
            link.close()

    def _connect(self) -> FrameAssembler:
        cfg = self.cfg
        group = cfg.resolved_group()
        self._links = [FlockLink(u, baud=cfg.baud, index=i, timing=self.timing, recorder=self._record,
                                 clock=self.clock)
                       for i, u in enumerate(cfg.urls)]
        for link in self._links:
            link.open(expected=self._identities.get(link.url))  # a reconnect refuses a port that changed
        setup = configure_flock(self._links, birds=cfg.birds, rate_hz=cfg.rate_hz if cfg.mode == "stream" else None,
                                record_format=cfg.record_format, group=group, mode=cfg.mode,
                                hemisphere=cfg.hemisphere, scale_inches=cfg.scale_inches, emit=self._emit)
        if cfg.mode == "point":
            # Frames come as often as we poll; the assembler needs that period, not the measurement rate.
            setup.rate_hz = float(cfg.rate_hz or min(setup.rate_hz, 20.0))
        self.setup = setup
        # What each port led to once a flock answered on it: what a reconnect must find again.
        self._identities.update({link.url: link.identity for link in self._links if link.identity is not None})
        options = dict(hemisphere_tracking=cfg.hemisphere_tracking, max_speed=cfg.max_speed,
                       max_turn_rate=cfg.max_turn_rate)
        with self._recording_lock:
            self._stream_marker = {"stream": setup.to_dict(), "assembler": options}
            if (rec := self._recorder) is not None:
                rec.mark(self.clock.monotonic(), self._stream_marker)
                rec.commit()
        asm = FrameAssembler(setup, words=cfg.tracker_words, **options)
        if cfg.mode == "stream":
            start_stream(self._links, setup)
        with self._lock:
            self._status = replace(self._status, connected=True, rate_hz=setup.rate_hz, record_format=setup.record_format,
                                   group=setup.group, scale_inches=setup.scale_inches, model=setup.model)
        self._connected_once.set()
        where = setup.urls[0] if len(setup.urls) == 1 else f"{len(setup.urls)} ports ({setup.urls[0]}, …)"
        self._emit("connected", f"{setup.birds} bird(s) on {where}: {setup.record_format}, "
                                f"{'group mode' if setup.group else 'one port per bird'}, {setup.rate_hz:.1f} Hz, "
                                f"{setup.mode} mode; {setup.model or 'unknown model'}, {setup.scale_inches:g}-inch "
                                f"scale{' (as the tracker was set)' if setup.scale_from_tracker else ''}",
                   birds=setup.birds, rate_hz=setup.rate_hz, record_format=setup.record_format, group=setup.group,
                   model=setup.model, scale_inches=setup.scale_inches)
        return asm

    def _session(self, asm: FrameAssembler) -> None:
        """Pump bytes from every port into the assembler until stopped; raises on a stall or lost port."""
        cfg = self.cfg
        q: queue.Queue = queue.Queue()
        quit_pumps = threading.Event()
        by_fd = {link.fileno(): link for link in self._links}
        direct = None not in by_fd
        if direct:
            # Ports with a descriptor (device paths, ptys) are read on this thread with select(): no
            # hand-over per read, and every port read in one wake-up is stamped with the same time, so
            # records of one cycle on different ports agree however late the thread runs.
            pumps = []
        else:
            pumps = [threading.Thread(target=self._pump, args=(link, q, quit_pumps), daemon=True,
                                      name=f"flockcal-pump-{link.index}") for link in self._links]
        for p in pumps:
            p.start()
        point = cfg.mode == "point"

        def receive(timeout: float) -> list:
            """(port, arrival time, bytes) read within `timeout` s; LinkLost (raised or queued) if a port is gone."""
            if direct:
                try:
                    ready, _, _ = select.select(list(by_fd), [], [], timeout)
                except (OSError, ValueError) as exc:
                    raise LinkLost(f"waiting for data failed: {exc}") from None
                t = self.clock.monotonic()
                return [(by_fd[fd].index, t, by_fd[fd].read_available()) for fd in ready]
            items = []
            if point:
                try:
                    items.append(q.get(timeout=timeout))
                except queue.Empty:
                    pass
            else:
                # Sleep until the next hand-over rather than waking for every read: the pumps stamp
                # each chunk on arrival, so batching here costs no timing precision.
                self.clock.wait(self._stop, timeout)
            while len(items) < 4096:
                try:
                    items.append(q.get_nowait())
                except queue.Empty:
                    break
            return items

        now = self.clock.monotonic()
        last_rx = np.full(len(self._links), now)
        last_batch = last_check = last_wake = now
        # Hand-overs happen only when there is something to hand over; stalls are looked for on this beat.
        check_period = min(0.05, cfg.stall_timeout / 4)
        setup = self.setup
        poll_period = 1.0 / setup.rate_hz
        expect = (setup.birds if setup.group else 1) * record_length(setup.record_format, group=setup.group)
        got_since_poll = np.full(len(self._links), expect)
        rate = RateCheck(setup, now) if not point else None
        next_poll = now
        poll_sent = now
        session_start = now
        try:
            while True:
                if self._stop.is_set():
                    # In point mode the last poll's answer may be on its way: let it finish (briefly),
                    # so the last frame is whole rather than missing its later birds.
                    if not point or (got_since_poll >= expect).all() or self.clock.monotonic() - poll_sent > 0.25:
                        break
                elif point:
                    now = self.clock.monotonic()
                    answered = (got_since_poll >= expect).all() or now - poll_sent > max(2 * poll_period, 0.25)
                    if now >= next_poll and answered:
                        poll(self._links, setup)
                        poll_sent = now
                        got_since_poll[:] = 0
                        next_poll = max(next_poll + poll_period, now)
                if point:
                    wait = 0.005
                elif not direct:  # pumps do not wake this thread: look again one hand-over interval on
                    wait = max(0.0, last_wake + cfg.batch_interval - self.clock.monotonic())
                elif asm.ready:
                    wait = max(0.0, last_batch + cfg.batch_interval - self.clock.monotonic())
                else:  # nothing to hand over: sleep until bytes come (or it is time to look for a stall)
                    wait = max(0.0, last_check + check_period - self.clock.monotonic())
                arrived = receive(wait)
                last_wake = self.clock.monotonic()
                for port, t, data in arrived:
                    if isinstance(data, Exception):
                        raise data
                    self._record(b"R", port, t, data)
                    asm.feed(port, t, data)
                    last_rx[port] = t
                    got_since_poll[port] += len(data)
                    if rate is not None:
                        rate.bytes += len(data)
                now = self.clock.monotonic()
                if asm.ready and now - last_batch >= cfg.batch_interval:
                    last_batch = now
                    self._deliver(asm)
                if now - last_check < check_period:
                    continue
                last_check = now
                if rate is not None and (warning := rate.check(now, asm.frames)):
                    self._emit("rate_low", warning, rate_hz=rate.measured_hz, asked_hz=setup.rate_hz)
                quiet = now - last_rx
                if (quiet > cfg.stall_timeout).any():
                    port = int(np.argmax(quiet))
                    self._emit("stalled", f"no data from {self._links[port].url} for {quiet[port]:.1f} s "
                                          f"— re-initialising the flock", port=port, seconds=float(quiet[port]))
                    raise _Stalled([0] if setup.group else [port])
                # A bird silent while others stream is usually a bird in error: stop and ask it.
                silent = now - np.maximum(asm.last_seen, session_start) > cfg.stall_timeout
                if silent.any() and not silent.all():
                    birds = [int(b) for b in np.flatnonzero(silent)]
                    self._emit("stalled", f"bird(s) {', '.join(map(str, birds))} sent no record for "
                                          f"{cfg.stall_timeout:g} s — asking for their error codes", birds=birds)
                    raise _Stalled(birds)
        finally:
            quit_pumps.set()
            for p in pumps:
                p.join(1.0)
        # Stopping: decode what already arrived, then leave the flock quiet.
        try:
            arrived = receive(0.0)
        except TrackerError:
            arrived = []
        for port, t, data in arrived:
            if not isinstance(data, Exception):
                self._record(b"R", port, t, data)
                asm.feed(port, t, data)
        stop_stream(self._links)

    def _ask_birds(self, birds: list[int]) -> None:
        """After a stall: read the error codes of the birds that went quiet (the reason, when they have one)."""
        try:
            stop_stream(self._links)
            for link in self._links:
                link.drain()
            found = check_bird_errors(self._links, self.setup, self._emit, birds=birds)
            if not found and len(birds) < self.setup.birds:
                names = ", ".join(str(b) for b in birds)
                self._emit("error", f"bird(s) {names} stopped sending but report no error — check their sensors "
                                    f"and cables", birds=birds)
        except TrackerError as exc:
            self._emit("error", f"while asking for error codes after a stall: {exc}")

    @staticmethod
    def _pump(link: FlockLink, q: queue.Queue, quit_pumps: threading.Event) -> None:
        name_os_thread(f"fc-pump-{link.index}")
        while not quit_pumps.is_set():
            try:
                t, data = link.read_some(record=False)
            except TrackerError as exc:
                q.put((link.index, link.clock.monotonic(), exc))
                return
            if data:
                q.put((link.index, t, data))
