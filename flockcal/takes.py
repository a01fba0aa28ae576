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

from flockcal import npz
from flockcal.atomic import replacing
from flockcal.errors import FlockcalError
from flockcal.frames import Frames


class TakeError(FlockcalError, ValueError):
    """A take file that is missing, unreadable or inconsistent."""


@dataclass(frozen=True)
class Take:
    """Frames of one recording, in SI units, validated on construction.

    Build one with `make_take` (which checks the arrays) or read one with `load_take`; a `Take` is
    frozen: derive another with `dataclasses.replace`. n frames of m sensors:

    Attributes
    ----------
    rotations : ndarray, shape (n, m, 3, 3)
        Each sensor's orientation, body to world (the transmitter's frame).
    positions : ndarray, shape (n, m, 3)
        Each sensor's position, metres.
    names : tuple of str
        The m sensor names, unique.
    rate_hz : float
        The nominal frame rate.
    valid : ndarray of bool, shape (n, m)
        False where a sensor-frame was not measured; its rotation and position hold zeros.
    times : ndarray, shape (n,)
        Seconds since the first frame, never going backwards.
    extra : dict
        Any further arrays the file carried, kept as they were.

    See Also
    --------
    flockcal.fit : fit a take.
    ChunkedTake : what reads a take a chunk of frames at a time; a Take is one.

    Examples
    --------
    >>> import flockcal
    >>> take, _ = flockcal.simulate(motion="exercise", seconds=2, birds=3, seed=1)
    >>> take.names, take.n_frames, take.rate_hz
    (('pelvis', 'chest', 'head'), 200, 100.0)
    >>> take.rotations.shape, take.positions.shape
    ((200, 3, 3, 3), (200, 3, 3))
    >>> take.index("head")
    2
    """

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
    """Build a validated `Take` from arrays.

    Parameters
    ----------
    rotations : array_like, shape (n, m, 3, 3)
        Each sensor's orientation as a rotation matrix, body to world.
    positions : array_like, shape (n, m, 3)
        Each sensor's position in metres.
    names : sequence of str
        The m sensor names: unique, none blank.
    rate_hz : float
        The frame rate, positive.
    valid : array_like of bool, shape (n, m), optional
        False where a sensor-frame was not measured (what it holds is then ignored and stored as
        zeros). By default every sensor-frame is valid.
    times : array_like, shape (n,), optional
        Seconds, never going backwards. By default ``arange(n) / rate_hz``.
    extra : dict, optional
        Further arrays to keep with the take (`save_take` writes them too).
    source : str, default "take"
        What the arrays came from, to begin each error message.

    Returns
    -------
    Take

    Raises
    ------
    flockcal.takes.TakeError
        Naming the first problem found: shapes that disagree, fewer than two sensors, repeated or blank
        names, a rate that is not a positive number, NaN or inf in a valid sensor-frame, times that go
        backwards.

    Examples
    --------
    >>> import numpy as np, flockcal
    >>> n = 100
    >>> rotations = np.broadcast_to(np.eye(3), (n, 2, 3, 3))
    >>> positions = np.zeros((n, 2, 3)); positions[:, 1, 0] = 0.3   # the second sensor 30 cm along x
    >>> take = flockcal.make_take(rotations, positions, ["upper_arm", "forearm"], rate_hz=100.0)
    >>> take.n_frames, take.n_sensors, float(take.times[-1])
    (100, 2, 0.99)
    >>> flockcal.make_take(rotations, positions, ["arm", "arm"], rate_hz=100.0)
    Traceback (most recent call last):
    flockcal.takes.TakeError: take: sensor names must be unique; repeated: arm
    """
    R = np.asarray(rotations, dtype=float)
    t = np.asarray(positions, dtype=float)
    names = tuple(str(x) for x in np.atleast_1d(np.asarray(names)).tolist())
    v = None if valid is None else np.asarray(valid)
    ts = None if times is None else np.asarray(times, dtype=float)
    n, m = check_shapes(source, R.shape, t.shape, len(names), None if v is None else v.shape,
                        None if ts is None else ts.shape)
    check_names(source, names)
    rate = check_rate(source, rate_hz)
    v = np.ones((n, m), dtype=bool) if v is None else v.astype(bool)
    check_finite(source, R, t, v, names)
    if ts is None:
        ts = np.arange(n, dtype=float) / rate
    else:
        check_times(source, ts)
    # Invalid sensor-frames may hold anything; store zeros so no NaN leaks into sums downstream.
    if not v.all():
        R = np.where(v[..., None, None], R, 0.0)
        t = np.where(v[..., None], t, 0.0)
    return Take(R, t, names, rate, v, ts, dict(extra or {}))


def check_shapes(source: str, rotations: tuple, positions: tuple, names: int, valid: tuple | None,
                 times: tuple | None) -> tuple[int, int]:
    """(n, m) when the arrays' shapes make a take (a Take's arrays, or an .npz's declared shapes read
    before its data); TakeError naming the first that does not."""
    if len(rotations) != 4 or tuple(rotations[2:]) != (3, 3):
        raise TakeError(f"{source}: 'rotations' must have shape (n, m, 3, 3), got {tuple(rotations)}")
    n, m = rotations[:2]
    if tuple(positions) != (n, m, 3):
        raise TakeError(f"{source}: 'positions' must have shape ({n}, {m}, 3) to match 'rotations', got "
                        f"{tuple(positions)}")
    if names != m:
        raise TakeError(f"{source}: 'names' has {names} entries but the arrays have {m} sensors")
    if m < 2:
        raise TakeError(f"{source}: needs at least two sensors to find a joint, got {m}")
    if n < 1:
        raise TakeError(f"{source}: the take has no frames")
    if valid is not None and tuple(valid) != (n, m):
        raise TakeError(f"{source}: 'valid' must have shape ({n}, {m}), got {tuple(valid)}")
    if times is not None and tuple(times) != (n,):
        raise TakeError(f"{source}: 'times' must have shape ({n},), got {tuple(times)}")
    return int(n), int(m)


def check_names(source: str, names: tuple[str, ...]) -> None:
    """TakeError unless the sensor names are unique and none is blank."""
    if len(set(names)) != len(names):
        dup = sorted({x for x in names if names.count(x) > 1})
        raise TakeError(f"{source}: sensor names must be unique; repeated: {', '.join(dup)}")
    if any(not x.strip() for x in names):
        raise TakeError(f"{source}: sensor names must not be empty")


def check_rate(source: str, rate_hz) -> float:
    rate = float(np.asarray(rate_hz))
    if not np.isfinite(rate) or rate <= 0:
        raise TakeError(f"{source}: 'rate_hz' must be a positive number, got {rate_hz!r}")
    return rate


def check_finite(source: str, R: np.ndarray, t: np.ndarray, v: np.ndarray, names, first: int | None = None) -> None:
    """TakeError when sensor-frames marked valid hold NaN or inf. `first`: R is a chunk of a take read piece
    by piece, starting at that frame (the count is then not known)."""
    bad = v & ~(np.isfinite(R).all(axis=(2, 3)) & np.isfinite(t).all(axis=2))
    if bad.any():
        k, i = np.argwhere(bad)[0]
        count = f"{int(bad.sum())} " if first is None else ""
        raise TakeError(
            f"{source}: {count}sensor-frames marked valid hold NaN or inf "
            f"(first: frame {(first or 0) + k}, sensor {names[i]!r}); mark them invalid with a 'valid' array"
        )


def check_times(source: str, ts: np.ndarray, before: float = -np.inf) -> None:
    """TakeError unless `ts` are finite and never go backwards (nor back past `before`, the time of the
    frame before them)."""
    if not np.isfinite(ts).all():
        raise TakeError(f"{source}: 'times' holds NaN or inf")
    if len(ts) and (ts[0] < before or np.any(np.diff(ts) < 0)):
        raise TakeError(f"{source}: 'times' must not go backwards")


def load_take(path: str | os.PathLike) -> Take:
    """Read a take: the .npz interchange of docs/design.md §5.

    Parameters
    ----------
    path : str or os.PathLike
        A .npz file holding `rotations`, `positions`, `names` and `rate_hz`, and optionally `valid` and
        `times` (what ``flockcal simulate``, ``flockcal convert`` and `save_take` write).

    Returns
    -------
    Take
        Its frames, checked as `make_take` checks them; arrays the file holds besides are in ``.extra``.

    Raises
    ------
    flockcal.takes.TakeError
        The file is missing, truncated, not an .npz, lacks an array or holds inconsistent ones. The
        message names the file and the fix.

    Examples
    --------
    >>> import pathlib, tempfile, flockcal
    >>> take, _ = flockcal.simulate(motion="exercise", seconds=2, birds=3, seed=1)
    >>> path = pathlib.Path(tempfile.mkdtemp()) / "take.npz"
    >>> flockcal.save_take(path, take)
    >>> back = flockcal.load_take(path)
    >>> back.names == take.names and bool((back.positions == take.positions).all())
    True
    >>> flockcal.load_take(path.with_name("absent.npz"))  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    flockcal.takes.TakeError: .../absent.npz: no such file
    """
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
    """Write a take as the .npz interchange of docs/design.md §5, atomically.

    The file is written beside `path` and renamed into place: a crash or a full disk never leaves a
    half-written file under `path`, and an old file there stays as it was until the new one is whole.

    Parameters
    ----------
    path : str or os.PathLike
        Where to write (conventionally ending in .npz). Its folder must exist.
    take : Take
        The take; its ``extra`` arrays are written too.

    Raises
    ------
    flockcal.atomic.OutputError
        The file could not be written (a folder that does not exist, a full disk); nothing is left behind.

    Examples
    --------
    >>> import pathlib, tempfile, flockcal
    >>> folder = pathlib.Path(tempfile.mkdtemp())
    >>> take, _ = flockcal.simulate(motion="walk", seconds=1, birds=2, seed=1)
    >>> flockcal.save_take(folder / "walk.npz", take)
    >>> sorted(p.name for p in folder.iterdir())          # the file, and no temporary one beside it
    ['walk.npz']
    >>> flockcal.save_take(folder / "no-such-folder" / "walk.npz", take)  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    flockcal.atomic.OutputError: cannot write .../no-such-folder/walk.npz: No such file or directory; ...
    """
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
    """Every array of an .npz file, or `error` saying it is truncated, not an .npz at all, or would unpack to
    more than the limit or the memory available (judged from its headers, before any data is read)."""
    if not zipfile.is_zipfile(path):
        raise error(f"{path}: not a .npz take (no complete zip archive of arrays: truncated, or not a take; {hint})")
    try:
        declared = npz.members(path)
        npz.check_size(declared, describe_arrays(declared), whole=True)
    except npz.NpzError as exc:
        raise error(f"{path}: {exc}") from None
    try:
        with np.load(path, allow_pickle=False) as data:
            return {k: data[k] for k in data.files}
    except (zipfile.BadZipFile, OSError, ValueError, EOFError) as exc:
        raise error(f"{path}: not a readable .npz take ({exc})") from None


def describe_arrays(arrays: dict) -> str:
    """What an archive's declared arrays hold, for a person: frames and sensors when it is a take."""
    rot = arrays.get("rotations")
    if rot is not None and len(rot.shape) >= 2:
        return f"{rot.shape[0]:,} frames of {rot.shape[1]:,} sensors"
    return f"{len(arrays)} arrays"


def write_npz(path: str | os.PathLike, **arrays) -> None:
    """Write arrays to a compressed .npz atomically: a crash never leaves a half-written file at `path`."""
    with replacing(path) as tmp, open(tmp, "wb") as fh:
        np.savez_compressed(fh, **arrays)
