"""Takes on disk a chunk of frames at a time, for takes of any length: `TakeFile` reads an .npz take as a
`ChunkedTake` (its shapes and size checked from the headers before any data, each chunk checked as
`make_take` checks a whole take), `TakeWriter` writes one from `Frames` as they come (a recording's decode).
"""

from __future__ import annotations

import os
import shutil
import tempfile
import weakref
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from flockcal import npz
from flockcal.frames import CHUNK_BYTES, Frames, chunk_frames, rechunked
from flockcal.takes import (TakeError, check_finite, check_names, check_rate, check_shapes, check_times,
                            describe_arrays)

class TakeFile:
    """A take .npz read a chunk of frames at a time, as often as asked: memory stays a chunk (and the
    names) whatever the take's length. Opening it reads the headers only: a file that is not a take, arrays
    whose shapes do not make one, or arrays that would unpack to more than the limit (`limit_gb`, else
    $FLOCKCAL_MAX_TAKE_GB, else 4 GB) are a TakeError before any frame is read. Bad values (NaN in a valid
    sensor-frame, times going backwards) are a TakeError when the chunk holding them is read."""

    def __init__(self, path: str | os.PathLike, limit_gb: float | None = None):
        self.path = Path(path)
        source = str(self.path)
        if not self.path.exists():
            raise TakeError(f"{source}: no such file")
        try:
            arrays = npz.members(self.path)
        except npz.NpzError:
            raise TakeError(f"{source}: not a .npz take (no complete zip archive of arrays: truncated, or not a "
                            f"take; takes come from np.savez, flockcal simulate or flockcal convert)") from None
        missing = [k for k in ("rotations", "positions", "names", "rate_hz") if k not in arrays]
        if missing:
            raise TakeError(f"{source}: missing array(s) {', '.join(missing)} (docs/design.md §5 lists what a take "
                            f"holds)")
        names = arrays["names"]
        self.n, self.m = check_shapes(source, arrays["rotations"].shape, arrays["positions"].shape,
                                      int(np.prod(names.shape, dtype=np.int64)),
                                      arrays["valid"].shape if "valid" in arrays else None,
                                      arrays["times"].shape if "times" in arrays else None)
        try:
            self.declared_bytes = npz.check_size(arrays, describe_arrays(arrays), limit_gb)
            with npz.Reader(self.path) as reader:
                self.names = tuple(str(x) for x in np.atleast_1d(reader.whole("names")).tolist())
                rate = reader.whole("rate_hz")
        except npz.NpzError as exc:
            raise TakeError(f"{source}: {exc}") from None
        check_names(source, self.names)
        self.rate_hz = check_rate(source, rate)
        self.has = {k for k in ("valid", "times") if k in arrays}
        self._spool: _Spool | None = None  # the checked arrays, once a pass has read them all
        # Its own chunks (size=None: what the exports play) are a quarter of a read chunk: reconstruction and
        # Euler angles hold ~10 arrays of a chunk's size (as the service's FrameFile.play_frames).
        self.chunk = chunk_frames(self.m, CHUNK_BYTES // 4)

    @property
    def n_frames(self) -> int:
        return self.n

    @property
    def n_sensors(self) -> int:
        return self.m

    def chunks(self, size: int | None = None) -> Iterator[Frames]:
        """The frames in order, `size` at a time (None: about 2 MB of arrays at a time). The first pass that
        reads the whole take from the zip also spools its checked arrays to a temporary folder; later passes
        read them from there, without inflating and checking them again (a pass over 20 minutes of 16
        sensors: 1.5 s from the zip; the disk holds the arrays once while the TakeFile lives)."""
        step = self.chunk if size is None else max(1, int(size))
        if self._spool is not None:
            yield from self._spool.chunks(step)
            return
        spool = _Spool.start(self.m)
        try:
            for f in self._from_zip(step):
                if spool is not None and not spool.add(f):
                    spool = None  # no room for it: later passes read the zip again
                yield f
            if spool is not None and self._spool is None:  # (another pass may have finished first)
                self._spool, spool = spool, None
                weakref.finalize(self, self._spool.discard)
        finally:
            if spool is not None:  # a pass that stopped early (or failed) spooled part of the take
                spool.discard()

    def _from_zip(self, step: int) -> Iterator[Frames]:
        source = str(self.path)
        try:
            with npz.Reader(self.path) as reader:
                streams = {k: reader.rows(k) for k in ("rotations", "positions", *sorted(self.has))}
                last = -np.inf
                for a in range(0, self.n, step):
                    k = min(step, self.n - a)
                    R = streams["rotations"].read(k).astype(float)
                    t = streams["positions"].read(k).astype(float)
                    v = streams["valid"].read(k).astype(bool) if "valid" in streams else np.ones((k, self.m), bool)
                    if "times" in streams:
                        ts = streams["times"].read(k).astype(float)
                        check_times(source, ts, before=last)
                        last = ts[-1]
                    else:
                        ts = np.arange(a, a + k, dtype=float) / self.rate_hz
                    check_finite(source, R, t, v, self.names, first=a)
                    if not v.all():  # as make_take: invalid sensor-frames hold zeros
                        R[~v] = 0.0
                        t[~v] = 0.0
                    yield Frames(ts, R, t, v)
        except npz.NpzError as exc:
            raise TakeError(f"{source}: not a readable .npz take ({exc})") from None

    def index(self, name: str) -> int:
        try:
            return self.names.index(name)
        except ValueError:
            raise TakeError(f"no sensor named {name!r} in this take (it has: {', '.join(self.names)})") from None


class _Spool:
    """A take's checked arrays in raw files of a temporary folder, read back a chunk at a time: what later
    passes over a TakeFile read instead of inflating the zip again."""

    FIELDS = (("times", np.float64, ()), ("rotations", np.float64, (3, 3)), ("positions", np.float64, (3,)),
              ("valid", np.bool_, ()))

    def __init__(self, folder: str, m: int):
        self.folder, self.m, self.n = folder, m, 0
        self.files = {name: open(os.path.join(folder, name), "wb") for name, _, _ in self.FIELDS}

    @classmethod
    def start(cls, m: int) -> "_Spool | None":
        try:
            return cls(tempfile.mkdtemp(prefix="flockcal-take-"), m)
        except OSError:
            return None

    def add(self, f: Frames) -> bool:
        """Append a chunk; False (and the spool gone) when the disk takes no more."""
        try:
            for name, _, _ in self.FIELDS:
                np.ascontiguousarray(getattr(f, name)).tofile(self.files[name])
        except OSError:
            self.discard()
            return False
        self.n += len(f)
        return True

    def chunks(self, step: int) -> Iterator[Frames]:
        for fh in self.files.values():
            fh.flush()
        files = {name: open(os.path.join(self.folder, name), "rb") for name, _, _ in self.FIELDS}
        try:
            for a in range(0, self.n, step):
                k = min(step, self.n - a)
                parts = []
                for name, dtype, shape in self.FIELDS:
                    rows = (k,) + ((self.m,) if name != "times" else ()) + shape
                    parts.append(np.fromfile(files[name], dtype=dtype, count=int(np.prod(rows))).reshape(rows))
                yield Frames(*parts)
        finally:
            for fh in files.values():
                fh.close()

    def discard(self) -> None:
        for fh in self.files.values():
            fh.close()
        shutil.rmtree(self.folder, ignore_errors=True)


class TakeWriter:
    """A take .npz written from `Frames` as they come: each batch checked as `make_take` checks a whole
    take (its sensors, NaN in valid sensor-frames, times going backwards), times counted from the first
    frame, invalid sensor-frames zeroed, and with `unfold` (a `HemisphereUnfold`) the hemisphere flips undone
    `unfold.CHUNK` frames at a time from the first, as unfolding the whole take does; `commit()` writes the
    file atomically (nothing is left at `path` before, or after a failure). Memory holds about a quarter
    chunk; the arrays wait on disk beside `path`."""

    def __init__(self, path: str | os.PathLike, names, rate_hz: float, source: str = "take",
                 extra: dict | None = None, unfold=None):
        self.source = source
        self.names = tuple(str(x) for x in names)
        check_names(source, self.names)
        self.rate_hz = check_rate(source, rate_hz)
        self.extra = dict(extra or {})
        self.unfold = unfold
        self._npz = npz.Writer(path)
        self._t0: float | None = None
        self._last = -np.inf
        self.n_frames = 0  # frames written (all appended ones after commit)
        self.valid_count = 0
        # Batches are gathered to whole blocks before they are checked and written: a recording's decode
        # hands over a few frames at a time, each write has its cost, and the unfolding decides per block.
        self._pending: list[Frames] = []
        self._pending_n = 0
        self._batch = unfold.CHUNK if unfold is not None else chunk_frames(len(self.names), CHUNK_BYTES // 4)

    def append(self, frames: Frames) -> None:
        if len(frames) == 0:
            return
        m = len(self.names)
        if frames.n_sensors != m:
            raise TakeError(f"{self.source}: frames of {frames.n_sensors} sensors after {m} names; a take keeps its "
                            f"sensors")
        self._pending.append(frames)
        self._pending_n += len(frames)
        if self._pending_n >= self._batch:
            self._write()

    def _write(self, final: bool = False) -> None:
        """Check and write the whole blocks gathered (and with `final` the rest too)."""
        if not self._pending:
            return
        whole = Frames.concat(self._pending, len(self.names))
        cut = len(whole) if final else len(whole) // self._batch * self._batch
        rest = whole[cut:]
        self._pending, self._pending_n = ([rest], len(rest)) if len(rest) else ([], 0)
        for a in range(0, cut, self._batch):
            self._block(whole[a:a + self._batch])

    def _block(self, frames: Frames) -> None:
        n = len(frames)
        R = np.asarray(frames.rotations, dtype=float)
        t = np.asarray(frames.positions, dtype=float)
        v = np.asarray(frames.valid, dtype=bool)
        check_finite(self.source, R, t, v, self.names, first=self.n_frames)
        if self._t0 is None:
            self._t0 = float(frames.times[0])
        ts = np.asarray(frames.times, dtype=float) - self._t0
        check_times(self.source, ts, before=self._last)
        self._last = float(ts[-1])
        if not v.all():
            R = np.where(v[..., None, None], R, 0.0)
            t = np.where(v[..., None], t, 0.0)
        if self.unfold is not None:
            t = self.unfold.feed(ts, t, v)
        for name, rows in (("rotations", R), ("positions", t), ("valid", v), ("times", ts)):
            self._npz.append(name, rows)
        self.n_frames += n
        self.valid_count += int(v.sum())

    @property
    def valid_fraction(self) -> float:
        return self.valid_count / max(1, self.n_frames * len(self.names))

    def commit(self) -> None:
        self._write(final=True)
        if self.n_frames == 0:
            self.discard()
            raise TakeError(f"{self.source}: the take has no frames")
        self._npz.put("names", np.asarray(self.names, dtype=str))
        self._npz.put("rate_hz", np.float64(self.rate_hz))
        for name, array in self.extra.items():
            self._npz.put(name, array)
        self._npz.commit()

    def discard(self) -> None:
        self._npz.discard()

    def __enter__(self) -> "TakeWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.discard()


class _Derived:
    """A ChunkedTake made from another as it is read: the same sensors, rate and frames."""

    def __init__(self, take):
        self.take, self.names, self.rate_hz = take, take.names, take.rate_hz

    @property
    def n_frames(self) -> int:
        return self.take.n_frames

    @property
    def n_sensors(self) -> int:
        return len(self.names)


class ScaledTake(_Derived):
    """A ChunkedTake whose positions are multiplied by `factor` as they are read (`fit --scale`)."""

    def __init__(self, take, factor: float):
        super().__init__(take)
        self.factor = float(factor)

    def chunks(self, size: int | None = None) -> Iterator[Frames]:
        for f in self.take.chunks(size):
            yield Frames(f.times, f.rotations, f.positions * self.factor, f.valid)


class UnfoldedTake(_Derived):
    """A ChunkedTake with its hemisphere flips undone as it is read (flockcal/hemisphere_unfold.py): each
    pass feeds a fresh `HemisphereUnfold` the frames `HemisphereUnfold.CHUNK` at a time from the first, whose
    decisions rest on those chunks, so every pass gives the positions unfolding the whole take gives."""

    def __init__(self, take, hemisphere: str | None = None):
        super().__init__(take)
        self.hemisphere = hemisphere

    def chunks(self, size: int | None = None) -> Iterator[Frames]:
        from flockcal.hemisphere_unfold import HemisphereUnfold

        unfold = HemisphereUnfold(len(self.names), self.hemisphere)
        step = HemisphereUnfold.CHUNK
        parts = (Frames(f.times, f.rotations, unfold.feed(f.times, f.positions, f.valid), f.valid)
                 for f in self.take.chunks(step))
        yield from rechunked(parts, step if size is None else max(1, int(size)), len(self.names))
