"""Frame sources the pipeline can listen to: the tracker reader (any pyserial URL, sim:// included).

A source calls `on_frames(frames)` with a `Frames` batch and `on_event(event)` for tracker news (a
`drivers.reader.TrackerEvent`), from its own thread; `status()` reports the link; `start_recording`
/ `stop_recording` write the raw bytes of one session. The pipeline does not care which source it has;
only a sim:// device gives a `simulator` (the performer, reached through the port the source opened).
"""

from __future__ import annotations

import dataclasses
import urllib.parse
from typing import TYPE_CHECKING, Callable, Protocol

from flockcal.clock import SYSTEM, Clock
from flockcal.drivers.tracker_status import TrackerStatus
from flockcal.drivers.port_guard import check_port
from flockcal.errors import FlockcalError
from flockcal.frames import Frames
from flockcal.server.errors import ConfigError
from flockcal.server.events import Event
from flockcal.server.settings import Settings

if TYPE_CHECKING:
    from flockcal.drivers.reader import TrackerEvent

OnFrames = Callable[[Frames], None]
OnEvent = Callable[["TrackerEvent"], None]


class FrameSource(Protocol):
    names: tuple[str, ...]

    def start(self, on_frames: OnFrames, on_event: OnEvent) -> None: ...

    def stop(self) -> None: ...

    def status(self) -> TrackerStatus: ...

    def start_recording(self, path) -> None: ...

    def stop_recording(self) -> None: ...


def sensor_names(settings: Settings, simulated: tuple[str, ...] | None = None) -> tuple[str, ...]:
    """Names given on the command line, else the simulated performer's, else bird1..birdN."""
    if settings.names:
        return tuple(settings.names)
    if simulated and len(simulated) == settings.birds:
        return tuple(simulated)
    return tuple(f"bird{i + 1}" for i in range(settings.birds))


def named_sim_url(url: str, name: str = "flockcal") -> str:
    """sim://?… → sim://flockcal?…: a named flock outlives its ports, so the reader's ports (and their
    re-opens on reconnect) stream the very performer the service holds for slips and routines."""
    parts = urllib.parse.urlsplit(url)
    if parts.scheme.lower() == "sim" and not parts.netloc:
        return urllib.parse.urlunsplit(("sim", name, parts.path, parts.query, parts.fragment))
    return url


def open_simulation(url: str, clock: Clock):
    """(the simulated performer, its fake flock) behind a sim:// URL, or None for any other device.

    The named simulation is made up front on the service's clock (so its sensor names are known, and its
    time is the reader's); the named flock outlives its ports, for the reader's ports (and their re-opens on
    reconnect) to stream.
    """
    if not url.lower().startswith("sim://"):
        return None
    import serial

    from flockcal.simulator.protocol_sim import simulation_for

    try:
        sim = simulation_for(url, clock)
    except (serial.SerialException, ValueError) as exc:
        raise ConfigError(f"--device {url}: {exc}") from None
    return sim.source, sim.flock


def tracker_event(event: TrackerEvent) -> Event:
    """The driver's news as the store and the websocket have it: an event of type "tracker" with the
    TrackerEvent's fields (kind, message, time, data), each JSON-able."""
    fields = dataclasses.asdict(event)
    return Event.new("tracker", **{k: v if isinstance(v, (str, int, float, bool, type(None), list, dict)) else str(v)
                                   for k, v in fields.items()})


class TrackerSource:
    """The driver's TrackerReader on `settings.device_url` (a sim:// URL gets a name and a control handle)."""

    def __init__(self, settings: Settings, recording_path=None, clock: Clock = SYSTEM):
        self.settings = settings
        self.clock = clock  # the reader's, and a simulation's: its frames are dated on the service's clock
        self.urls = [named_sim_url(u) for u in settings.device_urls]
        self.url = ",".join(self.urls)
        for url in self.urls:  # a port another program holds, or that leads elsewhere: refused before serving
            check_port(url)
        sim = open_simulation(self.urls[0], clock)
        self.simulator, self._flock = sim if sim is not None else (None, None)
        self.names = sensor_names(settings, self.simulator.names if self.simulator else None)
        self.reader = None
        self.recording_path = recording_path

    def reader_time(self, sim_time: float) -> float | None:
        """A simulated time on the reader's clock (the service's monotonic one), or None when the simulation
        runs on another clock. The reader dates each record on arrival, back-dated by the line's period, so the
        two agree to within a record's transfer time (a few ms at the simulator's baud rates)."""
        if self._flock is None or self._flock.clock is not self.clock:
            return None
        return float(sim_time) + self._flock.origin

    def start(self, on_frames: OnFrames, on_event: OnEvent) -> None:
        from flockcal.drivers.link import Timing
        from flockcal.drivers.reader import TrackerConfig, TrackerReader

        cfg = TrackerConfig(
            urls=self.urls,
            timing=Timing.fast() if self.settings.fast_init else None,
            batch_interval=self.settings.reader_batch_s,
            birds=self.settings.birds,
            rate_hz=self.settings.rate_hz,
            baud=self.settings.line_baud,
            hemisphere=self.settings.hemisphere,
            # The simulator's performer reaches past 36 in; a real tracker keeps the scale it is set to.
            scale_inches=self.settings.scale_inches or (72 if self.simulator is not None else None),
            recording_path=self.recording_path,
            tracker_words=True,  # the frame log stores them (server/frameblocks.py)
        )
        try:
            self.reader = TrackerReader(cfg, on_frames=on_frames,
                                        on_event=on_event,
                                        recording_header={"names": list(self.names)}, clock=self.clock)
        except FlockcalError as exc:
            raise ConfigError(f"--device {self.url}: {exc}") from None
        self.reader.start()

    def stop(self) -> None:
        if self.reader is not None:
            self.reader.stop()

    def start_recording(self, path) -> None:
        """Write the tracker's raw bytes from now on to the session file `path` (.fobraw)."""
        if self.reader is not None and self.recording_path is None:
            self.reader.start_recording(path, {"session_file": True})

    def stop_recording(self) -> None:
        if self.reader is not None and self.recording_path is None:
            self.reader.stop_recording()

    def status(self) -> TrackerStatus:
        if self.reader is None:
            return TrackerStatus(birds=self.settings.birds, last_error="not started")
        return self.reader.status()
