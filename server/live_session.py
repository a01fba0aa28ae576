"""The session being recorded: what it was started with, and the little the service keeps beside its
live calibration (solver/live.py). Touched only by the pipeline thread (server/pipeline.py) and the parts
it calls; other threads see it through the snapshots.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

from flockcal.clock import SYSTEM
from flockcal.server.framelog import FrameLog
from flockcal.server.fitting import FitView
from flockcal.solver.live import LiveCalibration
from flockcal.solver.progress import Profile


@dataclass
class LiveSession:
    """The session being recorded. Set when it starts (SessionManager.start): who, the tree it was given,
    its frame log and profile; `cal` when the pipeline installs it. Written afterwards only by the pipeline
    (`fit`, `fit_error`, `log_failed`, `slips`) and its persistence (`residual_rows`)."""

    id: str
    performer: str
    names: tuple[str, ...]
    hierarchy: dict | None
    root: str | None
    framelog: FrameLog
    profile: Profile
    skeleton: object = None  # a saved Skeleton: topology and bones fixed, only placements are fitted
    started_wall: float = field(default_factory=time.time)  # its created_at: a stamp shown to people
    started_mono: float = field(default_factory=SYSTEM.monotonic)  # on the service clock's monotonic(): durations
    cal: LiveCalibration | None = None  # the live calibration: accumulator, slip watch, residuals, progress
    fit: FitView | None = None  # the newest fit (`cal.calibration`), with its §5 dict made on first use
    fit_error: str | None = None
    residual_rows: list = field(default_factory=list)  # (time_s, {joint: mm}) not yet in the store
    slips: list = field(default_factory=list)  # the SlipEvents it reported, which its stored result lists
    log_failed: bool = False  # the frame log's write failure was reported (the log ended there)

    @property
    def frames(self) -> int:
        return self.cal.received if self.cal is not None else 0

    def summary(self) -> "SessionSummary":
        cal = self.cal
        progress = cal.progress if cal is not None else None
        return SessionSummary(
            id=self.id, performer=self.performer, frames=self.frames, started_at=self.started_wall,
            hierarchy=self.hierarchy, root=self.root, known_skeleton=self.skeleton is not None,
            profile=self.profile.name, progress=progress.progress if progress is not None else 0.0,
            done=progress is not None and progress.done, time_s=cal.time_s if cal is not None else 0.0,
            fit_error=self.fit_error)


@dataclass(frozen=True)
class SessionSummary:
    """The live session as a snapshot shows it; `to_dict()` is its JSON in the status and fit messages
    (docs/service.md)."""

    id: str
    performer: str
    frames: int
    started_at: float  # unix seconds
    hierarchy: dict | None
    root: str | None
    known_skeleton: bool
    profile: str
    progress: float  # the published figure, 0..1
    done: bool
    time_s: float  # session time of its newest frame
    fit_error: str | None  # why the newest refit failed, if it did

    def to_dict(self) -> dict:
        return {"id": self.id, "performer": self.performer, "state": "live", "frames": self.frames,
                "started_at": self.started_at, "hierarchy": self.hierarchy, "root": self.root,
                "known_skeleton": self.known_skeleton, "profile": self.profile, "progress": self.progress,
                "done": self.done, "time_s": self.time_s, "fit_error": self.fit_error}
