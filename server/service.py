"""The running service: settings, store, frame source, pipeline, sessions and the snapshot hub.

`Service.start()` marks sessions a dead process left live as interrupted, starts the pipeline and the
tracker reader; `stop()` closes any live session cleanly. FastAPI reads it from `app.state.service`.
"""

from __future__ import annotations

import errno
import fcntl
import logging
import os
from pathlib import Path

from flockcal.clock import SYSTEM, Clock
from flockcal.server.clock import ServiceClock
from flockcal.server.errors import ConfigError
from flockcal.server.events import Event
from flockcal.server.hub import SnapshotHub
from flockcal.server.limits import SessionLimits
from flockcal.server.outputs import Outputs
from flockcal.server.pipeline import Pipeline
from flockcal.server.retention import policy_from
from flockcal.server.sessions import SessionManager
from flockcal.server.settings import Settings
from flockcal.server.skeletons import SkeletonLibrary
from flockcal.server.snapshot import SourceStatus
from flockcal.server.sources import FrameSource, TrackerSource
from flockcal.server.store import SessionRow, Store

log = logging.getLogger(__name__)


def _lock_data_dir(data: Path) -> int:
    """One service per data directory: two writing the same sessions would corrupt each other's state."""
    path = data / "service.lock"
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as exc:
        raise ConfigError(f"cannot create {path}: {exc.strerror}; {_room_hint(exc, data)}") from None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        other = os.read(fd, 32).decode(errors="replace").strip() or "?"
        os.close(fd)
        raise ConfigError(f"another flockcal serve (pid {other}) uses the data directory {data}; "
                          "stop it or give --data-dir") from None
    try:
        os.ftruncate(fd, 0)
        os.write(fd, str(os.getpid()).encode())
    except OSError as exc:
        os.close(fd)
        raise ConfigError(f"cannot write {path}: {exc.strerror}; {_room_hint(exc, data)}") from None
    return fd


def _room_hint(exc: OSError, data: Path) -> str:
    if exc.errno in (errno.ENOSPC, errno.EDQUOT):
        return f"the disk holding {data} is full: make room there (or give --data-dir on another disk) and start again"
    return "check the folder's permissions, or give another --data-dir"


class Service:
    def __init__(self, settings: Settings, source: FrameSource | None = None, clock: Clock = SYSTEM):
        self.settings = settings.check()
        data = Path(settings.data_dir)
        data.mkdir(parents=True, exist_ok=True)
        self.data_dir = data
        self._lock_fd = _lock_data_dir(data)
        try:
            self.store = Store(data / "flockcal.sqlite3")  # damaged: DatabaseDamaged; full disk: InsufficientStorage
        except BaseException:
            os.close(self._lock_fd)
            raise
        try:
            # Stamps, durations, leases and retention ages all read this one clock (server/clock.py).
            self.clock = ServiceClock(clock, self.store)
        except BaseException:
            self.store.close()
            os.close(self._lock_fd)
            raise
        self.source = source if source is not None else TrackerSource(settings, clock=clock)
        self.interrupted = self.store.mark_interrupted()
        if self.interrupted:
            log.warning("sessions %s were live when the service last stopped; marked interrupted", ", ".join(self.interrupted))
        # Built in one pass, each part handed what it needs: nothing is wired in afterwards. The one way
        # back, a limit the pipeline finds stopping its session through the session manager, is given to
        # the pipeline when it starts (as the frame source gets the pipeline's feed).
        self.hub = SnapshotHub()
        self.limits = SessionLimits(data / "recordings", settings.max_session_s, settings.min_free_bytes,
                                    clock=self.clock)
        self.pipeline = Pipeline(
            self.source.names,
            self.store,
            self.status_of_source,
            publish_hz=settings.publish_hz,
            fit_hz=settings.fit_hz,
            residual_hz=settings.residual_hz,
            on_publish=self.hub.publish,
            rate_hz=self.tracker_rate,
            tolerance=settings.tolerance_m,
            target=settings.progress_target_m,
            limits=self.limits,
            clock=self.clock,
        )
        # A session records the rate the tracker streams at when it starts (the flock's own unless --rate).
        self.sessions = SessionManager(self.store, self.pipeline, data, settings.device_url, self.source_rate,
                                       profiles=settings.session_profile, raw_recorder=self.source,
                                       retention_policy=policy_from(settings.keep_days, settings.keep_disk_gb),
                                       retention_interval_s=settings.retention_interval_s, clock=self.clock)
        self.leases = self.sessions.leases  # sessions started with a lease end when their client stops renewing
        self.retention = self.sessions.retention  # prunes old sessions' frames and raw recordings between sessions
        try:
            self.skeletons = SkeletonLibrary(data / "skeletons", self.pipeline.names)
            for path in settings.skeletons:
                self.skeletons.load_file(path)
        except BaseException:
            # A bad --skeleton file stops the start: leave the data directory to the next attempt.
            self.store.close()
            os.close(self._lock_fd)
            raise
        # The live humanoid streams (VRPN, VMC), when asked for: bound now, so a port in use is said at start.
        self.outputs = (Outputs(settings, self.pipeline.names, lambda: self.pipeline.snapshot, self.clock)
                        if settings.vrpn_port is not None or settings.osc_targets else None)
        self.started = False
        self.stopped_session: SessionRow | None = None  # the session stop() closed, for `serve` to report

    def source_rate(self) -> float | None:
        """The rate the tracker streams at (its status's), else --rate's; None when neither is known."""
        return self.source.status().rate_hz or self.settings.rate_hz

    def tracker_rate(self) -> float:
        rate = self.source_rate()
        return float(rate) if rate else 100.0

    def status_of_source(self) -> SourceStatus:
        return SourceStatus(self.source.status(), self.settings.device_url, self.simulator is not None,
                            self.limits.disk_status())

    @property
    def simulator(self):
        """Handle on the simulated performer when the device is the simulator, else None."""
        return getattr(self.source, "simulator", None)

    def start(self) -> None:
        # A step of the wall clock is an event, and kept at once (the housekeeping pass saves the clock).
        self.clock.bind(self._clock_stepped)
        feed, beside = self.pipeline.feed, None
        if self.outputs is not None and self.outputs.active:
            self.outputs.start()
            feed, beside = self._feed_all, self.outputs.hand_over  # the streams' work rides on the pipeline's steps
        self.pipeline.start(stop_session=self.sessions.stop_for_limit, flush_held_rows=self.sessions.flush_held_rows,
                            beside=beside)
        self.source.start(feed, self.pipeline.tracker_event)
        self.retention.start()
        self.leases.start()
        self.started = True

    def _feed_all(self, frames) -> None:
        """The reader's batch to the pipeline and, queued for the pipeline's steps, to the live streams."""
        self.pipeline.feed(frames)
        self.outputs.feed(frames)
    def _clock_stepped(self, event: dict) -> None:
        # The clock writes its step as keyword fields (server/clock.py); Event.new's signature types them.
        self.pipeline.add_event(Event.new(**event))
        self.retention.wake()

    def stop(self) -> None:
        live = self.sessions.live_id()
        if live is not None:
            try:
                self.stopped_session = self.sessions.stop(live)
            except Exception:
                log.exception("could not stop session %s cleanly", live)
        self.retention.stop()
        self.leases.stop()
        try:
            self.source.stop()
        finally:
            if self.outputs is not None:
                self.outputs.stop()
            self.pipeline.stop()
            # What a full disk kept in memory, if there is room now; else the live session comes back
            # interrupted at the next start, its recording kept.
            if not (self.pipeline.persistence.flush_held() and self.sessions.flush_held_rows()):
                log.warning("the database could not take what was held in memory while the disk was full")
            try:
                self.clock.save()
            except Exception as exc:  # a full or damaged disk: the next start counts from the last save
                log.warning("the service clock could not be saved: %s", exc)
            self.store.close()
            os.close(self._lock_fd)
