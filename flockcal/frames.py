"""Frames: the one shape sensor data travels in, from the driver through the solver to the server.

n frames of m sensors as arrays (as scipy's Rotation holds many rotations in one object): times (n,),
rotations (n, m, 3, 3) body → world, positions (n, m, 3) metres, valid (n, m). No layer unpacks it into
loose arrays to hand it on.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

CHUNK_BYTES = 8 * 2**20  # frames per chunk of a take read piece by piece: about this much of float64 arrays
# Chunks hold a multiple of the accumulator's 256-frame block: its sums come out bit for bit the same
# whatever the chunk size, so `fit --json` of a file read in chunks is what it was for the whole take.
ROW_ALIGN = 256


@dataclass(frozen=True)
class TrackerWords:
    """The tracker's data words a batch's poses were decoded from: words (n, m, k) int32 of the record format
    whose command byte is `command`, at `scale_inches` (drivers/records.py `poses_from_words` of them gives
    the batch's rotations and positions bit for bit, wherever valid). The service's frame log stores these
    rather than working them out again from the floats."""

    words: np.ndarray
    command: int
    scale_inches: float

    def __getitem__(self, index) -> "TrackerWords":
        return TrackerWords(self.words[index], self.command, self.scale_inches)


@dataclass(frozen=True)
class Frames:
    """A batch of n frames of m sensors, SI units. Slots that are not valid hold zeros (parts a record
    format lacks may be NaN); readers of `rotations`/`positions` must look at `valid`."""

    times: np.ndarray  # (n,) seconds (the driver: monotonic arrival of the cycle's first byte)
    rotations: np.ndarray  # (n, m, 3, 3) body → world (the transmitter frame for a tracker)
    positions: np.ndarray  # (n, m, 3) metres
    valid: np.ndarray  # (n, m) bool
    words: TrackerWords | None = None  # what a tracker sent, when a reader was asked to keep it

    def __len__(self) -> int:
        return len(self.times)

    @property
    def n_frames(self) -> int:
        return len(self.times)

    @property
    def n_sensors(self) -> int:
        return self.rotations.shape[1]

    def __getitem__(self, index) -> "Frames":
        """Frames `index` (a slice, an index array or a boolean mask over frames), as Frames."""
        if isinstance(index, (int, np.integer)):
            index = slice(int(index), int(index) + 1 or None)
        return Frames(self.times[index], self.rotations[index], self.positions[index], self.valid[index],
                      None if self.words is None else self.words[index])

    @staticmethod
    def empty(m: int) -> "Frames":
        return Frames(np.zeros(0), np.zeros((0, m, 3, 3)), np.zeros((0, m, 3)), np.zeros((0, m), bool))

    @staticmethod
    def concat(parts: list["Frames"], m: int) -> "Frames":
        """One Frames from consecutive batches (`m` sensors when there are none)."""
        if not parts:
            return Frames.empty(m)
        if len(parts) == 1:
            return parts[0]
        words = None
        first = parts[0].words
        if first is not None and all(p.words is not None and (p.words.command, p.words.scale_inches)
                                     == (first.command, first.scale_inches) for p in parts):
            words = TrackerWords(np.concatenate([p.words.words for p in parts]), first.command, first.scale_inches)
        return Frames(*(np.concatenate([getattr(p, k) for p in parts])
                        for k in ("times", "rotations", "positions", "valid")), words)


def frames_of(take, size: int) -> Iterator[Frames]:
    """A take's frames in order, `size` at a time: its own `chunks(size)` when it has them (a Take, a
    flockcal.take_files.TakeFile, the service's frame log), else slices of its arrays (rotations,
    positions, and valid and times when it has them; times default to frame / rate_hz)."""
    if hasattr(take, "chunks"):
        yield from take.chunks(size)
        return
    R = np.asarray(take.rotations, dtype=float)
    t = np.asarray(take.positions, dtype=float)
    n, m = R.shape[:2]
    valid = getattr(take, "valid", None)
    valid = np.ones((n, m), bool) if valid is None else np.asarray(valid, dtype=bool)
    times = getattr(take, "times", None)
    times = np.arange(n) / float(take.rate_hz) if times is None else np.asarray(times, dtype=float)
    for a in range(0, n, max(1, int(size))):
        b = min(n, a + max(1, int(size)))
        yield Frames(times[a:b], R[a:b], t[a:b], valid[a:b])


def chunk_frames(m: int, budget: int = CHUNK_BYTES) -> int:
    """Frames of `m` sensors per chunk: about `budget` bytes of arrays, a multiple of ROW_ALIGN."""
    per_frame = m * (9 + 3) * 8 + m + 8
    return max(ROW_ALIGN, budget // per_frame // ROW_ALIGN * ROW_ALIGN)


def rechunked(parts: Iterator[Frames], size: int, m: int) -> Iterator[Frames]:
    """The frames of `parts` (batches of any lengths, in order) again, exactly `size` at a time (the last
    batch shorter)."""
    held: list[Frames] = []
    count = 0
    for part in parts:
        if not len(part):
            continue
        held.append(part)
        count += len(part)
        if count < size:
            continue
        whole, a = Frames.concat(held, m), 0
        while count - a >= size:
            yield whole[a:a + size]
            a += size
        held, count = ([whole[a:]], count - a) if count > a else ([], 0)
    if count:
        yield Frames.concat(held, m)
