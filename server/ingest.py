"""Frames in: the reader's batches joined, the frame count, the reader time of the newest frame and the
newest pose of every sensor (held from its last valid record), what the snapshots show with or without
a session. Pipeline thread only: the reader's hand-over queue is the pipeline's (server/pipeline.py).
"""

from __future__ import annotations

import numpy as np

from flockcal.frames import Frames


class Ingest:
    """Owns the frame count, the reader time of the newest frame and the newest pose."""

    def __init__(self, m: int):
        self.m = m
        self.frames = 0
        self.last_frame_time: float | None = None
        self.rotations = np.tile(np.eye(3), (m, 1, 1))
        self.positions = np.zeros((m, 3))
        self.valid = np.zeros(m, dtype=bool)
        self.have_pose = False

    def take(self, batches: list[Frames]) -> Frames | None:
        """The batches as one Frames (reader times), folded into the counts and the newest pose; None
        when they hold no frame."""
        f = Frames.concat(batches, self.m)
        n = len(f)
        if n == 0:
            return None
        valid = np.asarray(f.valid, dtype=bool)
        self.frames += n
        self.last_frame_time = float(f.times[-1])
        if valid[-1].all():  # the usual case: the newest frame holds every sensor's newest pose
            self.rotations[:] = f.rotations[-1]
            self.positions[:] = f.positions[-1]
            self.have_pose = True
            self.valid = valid[-1].copy()
            return f
        any_valid = valid.any(axis=0)
        if any_valid.any():
            last = n - 1 - np.argmax(valid[::-1], axis=0)
            cols = np.flatnonzero(any_valid)
            self.rotations[cols] = f.rotations[last[cols], cols]
            self.positions[cols] = f.positions[last[cols], cols]
            self.have_pose = True
        self.valid = valid[-1].copy()
        return f
