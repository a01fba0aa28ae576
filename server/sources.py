"""Frame sources the pipeline can listen to: the tracker reader (any pyserial URL, sim:// included).

A source calls `on_frames(times, rotations, positions, valid)` with arrays over a batch of frames and
`on_event(dict)` for tracker news, from its own thread; `status()` reports the link. The pipeline does
not care which source it has, so the server never needs to know hardware from simulator.
"""

from __future__ import annotations

import dataclasses
import logging
import time
import urllib.parse
from typing import Callable, Protocol

from flockcal.errors import FlockcalError
from flockcal.server.errors import ConfigError, ServerError
from flockcal.server.rawlog import SessionRawRecorder
from flockcal.server.settings import Settings

log = logging.getLogger(__name__)

OnFrames = Callable[..., None]
OnEvent = Callable[[dict], None]


class FrameSource(Protocol):
    names: tuple[str, ...]

    def start(self, on_frames: OnFrames, on_event: OnEvent) -> None: ...

    def stop(self) -> None: ...

    def status(self) -> dict: ...


def sensor_names(settings: Settings, simulated: tuple[str, ...] | None = None) -> tuple[str, ...]:
    """Names given on the command line, else the simulated performer's, else bird1..birdN."""
    if settings.names:
        return tuple(settings.names)
    if simulated and len(simulated) == settings.birds:
        return tuple(simulated)
    return tuple(f"bird{i + 1}" for i in range(settings.birds))


def named_sim_url(url: str, name: str = "flockcal") -> str:
    """sim://?… → sim://flockcal?… so the service can find its simulation again (slips, routines)."""
    parts = urllib.parse.urlsplit(url)
    if parts.scheme.lower() == "sim" and not parts.netloc:
        return urllib.parse.urlunsplit(("sim", name, parts.path, parts.query, parts.fragment))
    return url


class SimulatorControl:
    """The service's handle on a sim:// performer: inject a slip, change the routine."""

    def __init__(self, simulation):
        self.simulation = simulation

    @property
    def performer(self):
        return self.simulation.source

    @property
    def names(self) -> tuple[str, ...] | None:
        names = getattr(self.performer, "names", None)
        return tuple(names) if names is not None else None

    def inject_slip(self, sensor: str, distance_m: float) -> dict:
        """The performer's slip event; its `reader_time` is when it takes effect on the reader's clock."""
        if not hasattr(self.performer, "inject_slip"):
            raise ServerError("this simulated source cannot slip sensors", status=409)
        ev = self.performer.inject_slip(sensor, distance_m)
        ev["reader_time"] = self.reader_time(ev["time_s"])
        return ev

    def reader_time(self, sim_time: float) -> float | None:
        """A simulated time on the reader's clock (time.monotonic), or None if the simulation's clock is
        not the wall clock. The reader dates each record on arrival, back-dated by the line's period, so
        the two agree to within a record's transfer time (a few ms at the simulator's baud rates)."""
        from flockcal.simulator.fake_tracker import WallClock

        clock = self.simulation.flock.clock
        if not isinstance(clock, WallClock):
            return None
        return float(sim_time) + (time.monotonic() - clock())

    def set_routine(self, name: str) -> None:
        from flockcal.simulator.motion import ROUTINES, routine

        p = self.performer
        if name not in ROUTINES:
            raise ServerError(f"unknown routine {name!r}; choose one of {', '.join(ROUTINES)}", status=400)
        if not hasattr(p, "motion"):
            raise ServerError("this simulated source has no routines", status=409)
        old = p.motion
        p.motion = routine(p.model, name, 60.0, getattr(p, "rate_hz", 100.0), getattr(p, "seed", 0))
        log.info("simulated performer switched from %s to %s", getattr(old, "name", "?"), name)


def open_simulation(url: str) -> SimulatorControl | None:
    """Create the named simulation behind a sim:// URL up front (so its names are known), or None."""
    if not url.lower().startswith("sim://"):
        return None
    import serial

    import flockcal.simulator  # noqa: F401  (registers sim://)
    from flockcal.simulator.protocol_sim import get_simulation

    try:
        port = serial.serial_for_url(url)
        port.close()
    except (serial.SerialException, ValueError) as exc:
        raise ConfigError(f"--device {url}: {exc}") from None
    name = urllib.parse.urlsplit(url).netloc
    try:
        return SimulatorControl(get_simulation(name))
    except KeyError:
        return None


def event_dict(event) -> dict:
    """A TrackerEvent (dataclass or object) as a JSON-able dict with type 'tracker'."""
    if isinstance(event, dict):
        d = dict(event)
    elif dataclasses.is_dataclass(event):
        d = dataclasses.asdict(event)
    else:
        d = {k: v for k, v in vars(event).items() if not k.startswith("_")}
    if "type" in d and d["type"] != "tracker":
        d["kind"] = d.pop("type")
    d["type"] = "tracker"
    for k, v in list(d.items()):
        if not isinstance(v, (str, int, float, bool, type(None), list, dict)):
            d[k] = str(v)
    if "wall_time" in d and not isinstance(d["wall_time"], (int, float)):
        d.pop("wall_time")
    return d


class TrackerSource:
    """The driver's TrackerReader on `settings.device_url` (a sim:// URL gets a name and a control handle)."""

    def __init__(self, settings: Settings, recording_path=None):
        self.settings = settings
        self.urls = [named_sim_url(u) for u in settings.device_urls]
        self.url = ",".join(self.urls)
        self.simulator = open_simulation(self.urls[0])
        self.names = sensor_names(settings, self.simulator.names if self.simulator else None)
        self.reader = None
        self.recording_path = recording_path
        self.raw: SessionRawRecorder | None = None

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
        )
        try:
            self.reader = TrackerReader(cfg, on_frames=on_frames, on_event=lambda ev: on_event(event_dict(ev)))
        except FlockcalError as exc:
            raise ConfigError(f"--device {self.url}: {exc}") from None
        if cfg.recording_path is None and hasattr(self.reader, "_recorder"):
            # The reader has no call to switch recordings per session; fill its recorder slot once
            # with a forwarder that the session manager points at each session's .fobraw.
            self.raw = SessionRawRecorder(cfg.to_dict(), names=list(self.names))
            self.reader._recorder = self.raw
        self.reader.start()

    def stop(self) -> None:
        if self.reader is not None:
            self.reader.stop()

    def status(self) -> dict:
        if self.reader is None:
            return {"connected": False, "birds": self.settings.birds, "last_error": "not started"}
        return dict(self.reader.status())
