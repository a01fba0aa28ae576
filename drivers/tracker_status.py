"""The reader's account of its link, as `TrackerReader.status()` returns it: connected or not, at what rate
and in what record format, and its running counts (frames, dropped, rejected and saturated records, resyncs,
reconnects, bird errors). `doc` is its JSON, the tracker part of the service's /api/status.
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class TrackerStatus:
    connected: bool = False
    birds: int = 0
    rate_hz: float | None = None  # the flock's measurement rate, once connected
    frames: int = 0
    dropped_records: int = 0  # bird-frames without a valid record
    resynced: int = 0
    reconnects: int = 0
    last_error: str | None = None
    record_format: str | None = None
    urls: list[str] = field(default_factory=list)
    mode: str | None = None  # "stream" or "point"
    group: bool | None = None  # group mode (one port for the flock) or a port per bird
    rejected_records: int = 0
    dropped_bytes: int = 0
    bird_errors: int = 0
    recording_path: str | None = None
    saturated_records: int = 0
    scale_inches: float | None = None
    model: str | None = None  # the bird's model string, when it says

    @property
    def doc(self) -> dict:
        # Its fields in order, as asdict gives them, at 1/40 of asdict's 30 us (every snapshot, ~100 a second).
        return {**vars(self), "urls": list(self.urls)}
