"""Frames in: the newest pose of every sensor (held from its last valid record), and each batch folded
into the live session (frame log, accumulator). Pipeline thread only: the reader's hand-over queue is
the pipeline's (server/pipeline.py), this part sees the batches once that thread has taken them.
"""

from __future__ import annotations

import numpy as np

from flockcal.frames import Frames
from flockcal.server.fitting import accumulate
from flockcal.server.live_session import LiveSession


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

    def take(self, batches: list[Frames], live: LiveSession | None) -> tuple | None:
        """Fold the batches in; returns the live session's frames (session times, R, t, valid, with
        invalid slots zeroed) for the watchers, or None when no session is live or nothing came."""
        f = Frames.concat(batches, self.m)
        times = np.asarray(f.times, dtype=float)
        R = np.asarray(f.rotations, dtype=float)
        t = np.asarray(f.positions, dtype=float)
        valid = np.asarray(f.valid, dtype=bool)
        n = len(times)
        if n == 0:
            return None
        self.frames += n
        self.last_frame_time = float(times[-1])
        any_valid = valid.any(axis=0)
        if any_valid.any():
            last = n - 1 - np.argmax(valid[::-1], axis=0)
            cols = np.flatnonzero(any_valid)
            self.rotations[cols] = R[last[cols], cols]
            self.positions[cols] = t[last[cols], cols]
            self.have_pose = True
        self.valid = valid[-1].copy()
        if live is None:
            return None
        if live.t0 is None:
            live.t0 = float(times[0])
        live.framelog.write(times, R, t, valid)
        live.frames += n
        Rz = np.where(valid[..., None, None], R, 0.0)
        tz = np.where(valid[..., None], t, 0.0)
        ts = times - live.t0
        if live.watch is None:  # with a slip loop, the loop feeds the accumulator in its micro-batches
            accumulate(live.acc, ts, Rz, tz, valid)
        return ts, Rz, tz, valid

    def session_time(self, live: LiveSession) -> float:
        if live.t0 is None or self.last_frame_time is None:
            return 0.0
        return self.last_frame_time - live.t0
