"""The sample of a take that the humanoid finding reads (solver/humanoid.py): a bounded, evenly spread
`HumanoidSample` of its frames, fed a batch at a time live, or read from a take file by `take_sample`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flockcal.frames import Frames
from flockcal.frames import chunk_frames as frames_per_chunk

# The sample of the take the finding reads: a frame every SAMPLE_DT_S of the take's clock, at most
# SAMPLE_CAP of them (beyond that every other one is dropped and the spacing doubles, so the sample keeps
# covering the whole take): 0.85 MB for 16 sensors.
SAMPLE_DT_S = 0.1
SAMPLE_CAP = 512


@dataclass(frozen=True)
class Sample:
    """A snapshot of a `HumanoidSample`: its frames, and how many frames it had ever taken in (`seen`)."""

    frames: Frames
    seen: int


class HumanoidSample:
    """A bounded, evenly spread sample of a take's frames: one every `dt` seconds of its clock, at most `cap`;
    when full, every other frame goes and the spacing doubles. Fed a batch at a time (`add`); `frames()` is
    a snapshot that later `add`s never change (arrays are appended past it or replaced, never rewritten),
    so another thread may read it while frames keep coming. `seen` counts the frames ever taken in."""

    def __init__(self, n_sensors: int, dt: float = SAMPLE_DT_S, cap: int = SAMPLE_CAP):
        self.m = int(n_sensors)
        self.dt = float(dt)
        self.cap = max(2, int(cap) // 2 * 2)
        self._alloc(self.cap)
        self.n = 0
        self.seen = 0
        self._origin: float | None = None  # the first frame's time: the grid's zero
        self._cell = -np.inf  # the grid cell of the newest frame kept

    def _alloc(self, size: int) -> None:
        self.times = np.zeros(size)
        self.rotations = np.zeros((size, self.m, 3, 3))
        self.positions = np.zeros((size, self.m, 3))
        self.valid = np.zeros((size, self.m), dtype=bool)

    def add(self, frames: Frames) -> int:
        """Keep the frames of `frames` that fall on the sample's spacing; returns how many were kept. The
        spacing is a grid of `dt` from the first frame's time: the first frame in each cell is kept, so the
        sample depends on the frames alone, not on how they were batched."""
        ts = np.asarray(frames.times, dtype=float)
        # Live, a hand-over is a frame or two and reaches a new cell once in ~15: the others are passed at once.
        if self._origin is not None and len(ts) and np.floor((ts.max() - self._origin) / self.dt) <= self._cell:
            return 0
        kept, k0 = 0, 0
        while k0 < len(ts):
            if self._origin is None:
                self._origin = float(ts[k0])
            cells = np.floor((ts[k0:] - self._origin) / self.dt)
            # The first frame past the last kept cell and every frame that reaches a new one (a running max:
            # a clock that steps back enters no cell twice).
            reach = np.maximum.accumulate(np.concatenate([[self._cell], cells]))
            pick = k0 + np.flatnonzero(reach[1:] > reach[:-1])
            room = self.cap - self.n
            take = pick[:room]
            if len(take):
                v = np.asarray(frames.valid[take], dtype=bool)
                at = slice(self.n, self.n + len(take))
                self.times[at] = ts[take]
                self.rotations[at] = np.where(v[..., None, None], frames.rotations[take], 0.0)
                self.positions[at] = np.where(v[..., None], frames.positions[take], 0.0)
                self.valid[at] = v
                self.n += len(take)
                self.seen += len(take)
                kept += len(take)
                self._cell = float(cells[take[-1] - k0])
            if len(pick) <= room:
                break
            self._halve()
            k0 = int(pick[room])
        return kept

    def _halve(self) -> None:
        keep = slice(0, self.n, 2)
        old = (self.times[keep], self.rotations[keep], self.positions[keep], self.valid[keep])
        self._alloc(self.cap)  # new arrays: a snapshot of the old ones stays as it was
        k = len(old[0])
        self.times[:k], self.rotations[:k], self.positions[:k], self.valid[:k] = old
        self.n = k
        self.dt *= 2.0
        self._cell = float(np.floor((self.times[k - 1] - self._origin) / self.dt))

    def frames(self) -> Frames:
        """The sample so far (views: valid while the sample lives, never rewritten)."""
        n = self.n
        return Frames(self.times[:n], self.rotations[:n], self.positions[:n], self.valid[:n])

    def snapshot(self) -> Sample:
        """The sample so far, for a fit on another thread (no copy: see the class)."""
        return Sample(self.frames(), self.seen)


def take_sample(take, dt: float = SAMPLE_DT_S, cap: int = SAMPLE_CAP, chunk_frames: int | None = None) -> HumanoidSample:
    """The sample of a `flockcal.takes.ChunkedTake` (a Take, a take file, or the service's frame log), read
    through its `chunks` (None: `flockcal.frames.chunk_frames`, about 8 MB of arrays, which keeps a take
    file's memory to its budget; the sample does not depend on them): what `flockcal fit` and the exports
    find the humanoid from, as the service does from its frames."""
    sample = HumanoidSample(len(take.names), dt, cap)
    for f in take.chunks(chunk_frames or frames_per_chunk(len(take.names))):
        sample.add(f)
    return sample
