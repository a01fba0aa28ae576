"""The .npz take interchange of docs/design.md §5: load, validate and save recorded frames.

A take is n frames of m sensors: rotations (n, m, 3, 3) body→world, positions (n, m, 3) metres,
valid (n, m), times (n,) seconds, names (m,), rate_hz. Every problem found gets a one-line `TakeError`.
`ChunkedTake` is what reads a take a chunk of frames at a time (the exports); a `Take` is one.
"""

from __future__ import annotations

import os
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator, Protocol, runtime_checkable

import numpy as np

from flockcal.atomic import replacing
from flockcal.errors import FlockcalError
from flockcal.frames import Frames


class TakeError(FlockcalError, ValueError):
    """A take file that is missing, unreadable or inconsistent."""


@dataclass(frozen=True)
class Take:
    """Frames of one recording, in SI units, validated on construction."""

    rotations: np.ndarray  # (n, m, 3, 3) float64
    positions: np.ndarray  # (n, m, 3) float64, metres
    names: tuple[str, ...]  # (m,)
    rate_hz: float
    valid: np.ndarray  # (n, m) bool
    times: np.ndarray  # (n,) float64, seconds since start
    extra: dict = field(default_factory=dict)  # any further arrays the file carried

    @property
    def n_frames(self) -> int:
        return self.rotations.shape[0]

    @property
    def n_sensors(self) -> int:
        return self.rotations.shape[1]

    def chunks(self, size: int | None = None) -> Iterator[Frames]:
        """The take's frames as `Frames` of `size` frames (views, not copies); None: all of them at once."""
        n = self.n_frames
        step = n if size is None else max(1, int(size))
        for a in range(0, n, max(step, 1)):
            b = a + step
            yield Frames(self.times[a:b], self.rotations[a:b], self.positions[a:b], self.valid[a:b])

    def index(self, name: str) -> int:
        """Sensor index of `name`, or a TakeError listing the names the take has."""
        try:
            return self.names.index(name)
        except ValueError:
            raise TakeError(f"no sensor named {name!r} in this take (it has: {', '.join(self.names)})") from None


@runtime_checkable
class ChunkedTake(Protocol):
    """A take read a chunk of frames at a time, as often as asked: a `Take` in memory, or the service's
    frame log on disk (server/downloads.py `FrameFile`), whose memory stays a chunk whatever its length.
    Chunks hold what a Take holds: times from the first frame, invalid sensor-frames zeroed."""

    names: tuple[str, ...] | list[str]
    rate_hz: float

    @property
    def n_frames(self) -> int: ...

    def chunks(self, size: int | None = None) -> Iterator[Frames]:
        """The frames in order, `size` at a time (None: the reader's own chunk)."""
        ...


def make_take(
    rotations,
    positions,
    names,
    rate_hz: float,
    valid=None,
    times=None,
    extra: dict | None = None,
    source: str = "take",
) -> Take:
    """Build a validated Take from arrays; raises TakeError naming the first problem found."""
    R = np.asarray(rotations, dtype=float)
    t = np.asarray(positions, dtype=float)
    if R.ndim != 4 or R.shape[2:] != (3, 3):
        raise TakeError(f"{source}: 'rotations' must have shape (n, m, 3, 3), got {R.shape}")
    n, m = R.shape[:2]
    if t.shape != (n, m, 3):
        raise TakeError(f"{source}: 'positions' must have shape ({n}, {m}, 3) to match 'rotations', got {t.shape}")
    names = tuple(str(x) for x in np.atleast_1d(np.asarray(names)).tolist())
    if len(names) != m:
        raise TakeError(f"{source}: 'names' has {len(names)} entries but the arrays have {m} sensors")
    if m < 2:
        raise TakeError(f"{source}: needs at least two sensors to find a joint, got {m}")
    if len(set(names)) != m:
        dup = sorted({x for x in names if names.count(x) > 1})
        raise TakeError(f"{source}: sensor names must be unique; repeated: {', '.join(dup)}")
    if any(not x.strip() for x in names):
        raise TakeError(f"{source}: sensor names must not be empty")
    if n < 1:
        raise TakeError(f"{source}: the take has no frames")
    rate = float(np.asarray(rate_hz))
    if not np.isfinite(rate) or rate <= 0:
        raise TakeError(f"{source}: 'rate_hz' must be a positive number, got {rate_hz!r}")
    if valid is None:
        v = np.ones((n, m), dtype=bool)
    else:
        v = np.asarray(valid)
        if v.shape != (n, m):
            raise TakeError(f"{source}: 'valid' must have shape ({n}, {m}), got {v.shape}")
        v = v.astype(bool)
    finite = np.isfinite(R).all(axis=(2, 3)) & np.isfinite(t).all(axis=2)
    bad = v & ~finite
    if bad.any():
        k, i = np.argwhere(bad)[0]
        raise TakeError(
            f"{source}: {int(bad.sum())} sensor-frames marked valid hold NaN or inf "
            f"(first: frame {k}, sensor {names[i]!r}); mark them invalid with a 'valid' array"
        )
    if times is None:
        ts = np.arange(n, dtype=float) / rate
    else:
        ts = np.asarray(times, dtype=float)
        if ts.shape != (n,):
            raise TakeError(f"{source}: 'times' must have shape ({n},), got {ts.shape}")
        if not np.isfinite(ts).all():
            raise TakeError(f"{source}: 'times' holds NaN or inf")
        if n > 1 and np.any(np.diff(ts) < 0):
            raise TakeError(f"{source}: 'times' must not go backwards")
    # Invalid sensor-frames may hold anything; store zeros so no NaN leaks into sums downstream.
    if not v.all():
        R = np.where(v[..., None, None], R, 0.0)
        t = np.where(v[..., None], t, 0.0)
    return Take(R, t, names, rate, v, ts, dict(extra or {}))


def load_take(path: str | os.PathLike) -> Take:
    """Read a take .npz; raises TakeError for a missing, corrupt or inconsistent file."""
    path = Path(path)
    if not path.exists():
        raise TakeError(f"{path}: no such file")
    arrays = read_npz(path, TakeError, "takes come from np.savez, flockcal simulate or flockcal convert")
    missing = [k for k in ("rotations", "positions", "names", "rate_hz") if k not in arrays]
    if missing:
        raise TakeError(f"{path}: missing array(s) {', '.join(missing)} (docs/design.md §5 lists what a take holds)")
    known = {"rotations", "positions", "names", "rate_hz", "valid", "times"}
    return make_take(
        arrays["rotations"],
        arrays["positions"],
        arrays["names"],
        arrays["rate_hz"],
        valid=arrays.get("valid"),
        times=arrays.get("times"),
        extra={k: v for k, v in arrays.items() if k not in known},
        source=str(path),
    )


def save_take(path: str | os.PathLike, take: Take) -> None:
    """Write a take .npz (atomically: a crash never leaves a half-written file under `path`)."""
    write_npz(
        path,
        rotations=take.rotations,
        positions=take.positions,
        names=np.asarray(take.names, dtype=str),
        rate_hz=np.float64(take.rate_hz),
        valid=take.valid,
        times=take.times,
        **take.extra,
    )


def read_npz(path: Path, error: type[Exception], hint: str) -> dict:
    """Every array of an .npz file, or `error` saying it is truncated or not an .npz at all."""
    if not zipfile.is_zipfile(path):
        raise error(f"{path}: not a .npz take (no complete zip archive of arrays: truncated, or not a take; {hint})")
    try:
        with np.load(path, allow_pickle=False) as data:
            return {k: data[k] for k in data.files}
    except (zipfile.BadZipFile, OSError, ValueError, EOFError) as exc:
        raise error(f"{path}: not a readable .npz take ({exc})") from None


def write_npz(path: str | os.PathLike, **arrays) -> None:
    """Write arrays to a compressed .npz atomically: a crash never leaves a half-written file at `path`."""
    with replacing(path) as tmp, open(tmp, "wb") as fh:
        np.savez_compressed(fh, **arrays)
