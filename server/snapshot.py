"""The immutable snapshot the pipeline publishes: everything a client may read about the live state,
and `SnapshotMaker`, the pipeline's part that builds them.

API handlers and websocket senders only ever read the newest Snapshot; derived views (the pose, the
JSON bodies) are computed on first use and cached on the snapshot, so 50 clients cost one encoding.
"""

from __future__ import annotations

import json
from collections import deque
from dataclasses import dataclass
from functools import cached_property
from typing import Callable

import numpy as np

from flockcal.drivers.tracker_status import TrackerStatus
from flockcal.server.events import Event
from flockcal.server.fitting import FitView
from flockcal.server.limits import DiskStatus
from flockcal.server.live_session import SessionSummary
from flockcal.server.pose import live_pose
from flockcal.solver.calibration import Calibration
from flockcal.solver.live import JointResiduals
from flockcal.solver.progress import Progress, waiting

RECENT_RESIDUALS = 400


@dataclass(frozen=True, eq=False)
class ResidualSample:
    seq: int
    time_s: float  # session clock
    rms_mm: dict  # {joint child name: rms over the sample interval, mm}

    @staticmethod
    def of(seq: int, sample: JointResiduals) -> "ResidualSample":
        """A live calibration's sample as clients and the store get it: mm to 4 decimals, joints with no
        valid frame left out."""
        mm = sample.rms_m * 1000.0
        return ResidualSample(seq, sample.time_s, {j[0]: round(float(v), 4) for j, v in zip(sample.joints, mm)
                                                   if v == v})


@dataclass(frozen=True)
class SourceStatus:
    """The frame source's part of the status: the reader's link, the device it was given (a URL), whether
    that is the simulator, and the disk the recordings go to."""

    tracker: TrackerStatus
    device: str
    simulator: bool
    disk: DiskStatus

    @property
    def doc(self) -> dict:
        return {**self.tracker.doc, "device": self.device, "simulator": self.simulator, "disk": self.disk.doc}


@dataclass(frozen=True, eq=False)
class Snapshot:
    seq: int  # increases with every publish
    wall_time: float  # unix seconds at publish (the service clock's stamp: never steps back)
    frames: int  # frames received since the service started
    last_frame_time: float | None  # reader clock of the newest frame
    status: dict  # tracker status + pipeline figures + live session summary
    session: SessionSummary | None  # the live session, None when none is live
    names: tuple[str, ...]
    fit_view: FitView | None  # the live session's newest fit
    fit_seq: int  # increases when the fit changes
    residuals: tuple[ResidualSample, ...]  # recent samples, oldest first
    events: tuple[Event, ...]  # recent events (each with its store id), oldest first
    rotations: np.ndarray | None  # newest pose of each sensor (m,3,3) (held where invalid)
    positions: np.ndarray | None  # (m,3)
    valid: np.ndarray | None  # (m,) whether the newest frame held a valid record for each sensor
    pose_fit: Calibration | None = None  # fit used to draw the skeleton (live or the last stopped session's)
    pose_fit_id: tuple | None = None  # (session id, fit_seq or None for its stored final fit) of pose_fit
    progress: Progress | None = None  # the live session's progress (solver/progress.py), None without one
    source: SourceStatus | None = None  # what `status` was made of (None: the source's status failed)

    @property
    def connected(self) -> bool:
        return self.source is not None and self.source.tracker.connected

    @property
    def disk_full(self) -> bool:
        return self.source is not None and self.source.disk.full

    @property
    def has_fit(self) -> bool:
        return self.fit_view is not None

    @property
    def fit(self) -> dict | None:
        """design.md §5 JSON of the live session's newest fit (made once per fit, on first use)."""
        return None if self.fit_view is None else self.fit_view.doc

    @cached_property
    def progress_doc(self) -> dict | None:
        """The progress as the service publishes it (docs/service.md), None without a live session."""
        return None if self.progress is None else self.progress.to_dict()

    @cached_property
    def pose(self) -> dict | None:
        if self.rotations is None:
            return None
        return live_pose(list(self.names), self.rotations, self.positions, self.valid, self.pose_fit,
                         fit_id=self.pose_fit_id)

    # JSON bodies without their envelope: a sender splices in type, seq and time per connection.
    @cached_property
    def status_json(self) -> str:
        return json.dumps({"status": self.status, "snapshot": self.seq, "frames": self.frames})

    @cached_property
    def fit_json(self) -> str:
        # The progress document's fields ride at the top level next to the fit: "progress" stays the number
        # it always was, now the service's one definition (docs/service.md#progress-one-figure-for-the-kiosk-the-dashboard-and-the-api).
        return json.dumps({
            "result": self.fit, **(self.progress_doc or {"hints": []}),
            "session": None if self.session is None else self.session.to_dict(), "fit_seq": self.fit_seq,
            "snapshot": self.seq, "frames": self.frames,
        })

    @cached_property
    def pose_json(self) -> str:
        return json.dumps({"pose": self.pose, "snapshot": self.seq, "frames": self.frames,
                           "frame_time": self.last_frame_time})


def residual_message(samples: list[ResidualSample]) -> dict:
    """{times: [...], joints: {child: [mm|None, ...]}} aligned on times (the dashboard's plot shape)."""
    names = sorted({k for s in samples for k in s.rms_mm})
    return {
        "times": [round(s.time_s, 4) for s in samples],
        "joints": {k: [s.rms_mm.get(k) for s in samples] for k in names},
        "last": samples[-1].seq if samples else None,
    }


class SnapshotMaker:
    """Builds each Snapshot from the pipeline's parts and swaps it in with one reference assignment.

    `make` runs on the pipeline thread (which owns `seq`); any thread reads `current`, which is only ever
    replaced, never changed: the event loop never waits for the pipeline."""

    def __init__(self, names, source_status: Callable[[], SourceStatus], target: float, stamp: Callable[[], float]):
        self.names = tuple(names)
        self.stamp = stamp
        self.source_status = source_status
        self.target = target
        self.seq = 0
        self.current: Snapshot | None = None
        # The newest residual samples, numbered across sessions (a websocket sends those past its last).
        self.residuals: deque[ResidualSample] = deque(maxlen=RECENT_RESIDUALS)
        self._residual_seq = 0

    def add_residuals(self, samples) -> list[ResidualSample]:
        """Number the live calibration's samples and keep them for the snapshots; returns them numbered."""
        out = []
        for sample in samples:
            self._residual_seq += 1
            out.append(ResidualSample.of(self._residual_seq, sample))
        self.residuals.extend(out)
        return out

    def make(self, *, live, ingest, persistence, fit_seq: int,
             fits_done: int, fit_seconds: float, pose_fit, pose_fit_id=None) -> Snapshot:
        self.seq += 1
        try:
            source = self.source_status()
            tracker = source.doc
        except Exception as exc:  # the status of a source that failed is itself news
            source, tracker = None, {"connected": False, "last_error": f"status unavailable: {exc}"}
        session = None
        progress = None
        if live is not None:
            session = live.summary()
            progress = live.cal.progress or waiting(self.names, self.target, live.fit_error or "no fit yet: keep moving")
        status = dict(tracker)
        status.update(
            frames=ingest.frames,
            session=None if session is None else session.to_dict(),
            sensors=list(self.names),
            fits=fits_done,
            fit_ms=round(1000 * fit_seconds / fits_done, 3) if fits_done else None,
        )
        self.current = Snapshot(
            seq=self.seq,
            wall_time=self.stamp(),
            frames=ingest.frames,
            last_frame_time=ingest.last_frame_time,
            status=status,
            session=session,
            names=self.names,
            fit_view=live.fit if live is not None else None,
            fit_seq=fit_seq,
            residuals=tuple(self.residuals),
            events=tuple(persistence.recent),
            rotations=ingest.rotations.copy() if ingest.have_pose else None,
            positions=ingest.positions.copy() if ingest.have_pose else None,
            valid=ingest.valid.copy(),
            pose_fit=pose_fit,
            pose_fit_id=pose_fit_id,
            progress=progress,
            source=source,
        )
        return self.current
