"""The session being recorded: its mutable state, touched only by the pipeline thread (server/pipeline.py)
and the parts it calls; other threads see it through the snapshots.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

from flockcal.server.framelog import FrameLog
from flockcal.solver.calibration import Calibration
from flockcal.solver.progress import Profile, Progress
from flockcal.solver.progress_tracker import ProgressTracker
from flockcal.solver.slippage.watch import SlipWatch


@dataclass
class LiveSession:
    """Mutable state of the session being recorded; touched only by the pipeline thread."""

    id: str
    performer: str
    names: tuple[str, ...]
    hierarchy: dict | None
    root: str | None
    framelog: FrameLog
    skeleton: object = None  # a saved Skeleton: topology and bones fixed, only placements are fitted
    acc: object = None  # GramAccumulator or SegmentedAccumulator, made on install
    watch: SlipWatch | None = None  # the slip loop; when present it feeds `acc` (a SegmentedAccumulator)
    t0: float | None = None  # reader time of the session's first frame
    frames: int = 0
    started_wall: float = field(default_factory=time.time)
    fit: dict | None = None  # the newest fit's §5 dict (clients, the store)
    calibration: Calibration | None = None  # the same fit, typed (what the service computes with)
    fit_error: str | None = None
    fit_frames: int = 0  # accumulator frames the newest fit used
    residual_rows: list = field(default_factory=list)  # (time_s, {joint: mm}) not yet in the store
    tracker: ProgressTracker | None = None  # the session's progress, made on install
    progress: Progress | None = None  # its newest (solver/progress.py); None before the first fit
    slip_epoch: int = 0  # slips applied to the accumulator so far: fits carry the epoch they were begun in
    log_failed: bool = False  # the frame log's write failure was reported (the log ended there)
    profile: Profile | None = None  # how it decides it is calibrated (solver/progress.py); None: the pipeline's stage

    def summary(self) -> dict:
        return {
            "id": self.id, "performer": self.performer, "state": "live", "frames": self.frames,
            "started_at": self.started_wall,
            "hierarchy": self.hierarchy, "root": self.root,
            "known_skeleton": self.skeleton is not None,
            "profile": self.profile.name if self.profile else "stage",
            "progress": self.progress.progress if self.progress is not None else 0.0,
            "done": self.progress is not None and self.progress.done,
        }
