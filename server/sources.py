"""Frame sources the pipeline can listen to: the tracker reader (any pyserial URL, sim:// included).

A source calls `on_frames(times, rotations, positions, valid)` with arrays over a batch of frames and
`on_event(dict)` for tracker news, from its own thread; `status()` reports the link. The pipeline does
not care which source it has, so the server never needs to know hardware from simulator.
"""

from __future__ import annotations

import dataclasses
import logging
from typing import Callable, Protocol

from flockcal.server.settings import Settings

log = logging.getLogger(__name__)

OnFrames = Callable[..., None]
OnEvent = Callable[[dict], None]


class FrameSource(Protocol):
    names: tuple[str, ...]

    def start(self, on_frames: OnFrames, on_event: OnEvent) -> None: ...

    def stop(self) -> None: ...

    def status(self) -> dict: ...


def sensor_names(settings: Settings) -> tuple[str, ...]:
    """Names given on the command line, else the simulated body's (for sim://), else bird1..birdN."""
    if settings.names:
        return tuple(settings.names)
    if settings.device_url.startswith("sim://"):
        try:
            from flockcal.simulator.body import human

            names = tuple(human(n_bodies=settings.birds).names)
            if len(names) == settings.birds:
                return names
        except Exception as exc:  # an unusual bird count: fall back to numbered birds
            log.info("simulator body names unavailable for %d birds: %s", settings.birds, exc)
    return tuple(f"bird{i + 1}" for i in range(settings.birds))


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
    """The driver's TrackerReader on `settings.device_url`."""

    def __init__(self, settings: Settings, recording_path=None):
        self.settings = settings
        self.names = sensor_names(settings)
        self.reader = None
        self.recording_path = recording_path

    def start(self, on_frames: OnFrames, on_event: OnEvent) -> None:
        from flockcal.drivers.reader import TrackerConfig, TrackerReader

        cfg = TrackerConfig(
            urls=[self.settings.device_url],
            birds=self.settings.birds,
            rate_hz=self.settings.rate_hz,
            baud=self.settings.baud,
            hemisphere=self.settings.hemisphere,
            recording_path=self.recording_path,
        )
        self.reader = TrackerReader(cfg, on_frames=on_frames, on_event=lambda ev: on_event(event_dict(ev)))
        self.reader.start()

    def stop(self) -> None:
        if self.reader is not None:
            self.reader.stop()

    def status(self) -> dict:
        if self.reader is None:
            return {"connected": False, "birds": self.settings.birds, "last_error": "not started"}
        return dict(self.reader.status())
