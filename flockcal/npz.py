"""Reading and writing .npz archives a piece at a time: the arrays an archive declares (its .npy headers,
read before any data), rows streamed out of one member, and a writer that appends rows to members of a
length not known in advance and zips them at the end. Memory stays a chunk whatever the arrays' sizes.
"""

from __future__ import annotations

import os
import shutil
import tempfile
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.lib import format as npy

from flockcal.atomic import replacing

COPY_BYTES = 1 << 20
MAX_HEADER = 100_000  # numpy's own default limit is 10,000; a take's headers are ~100 bytes


class NpzError(ValueError):
    """An archive that is not a readable .npz (the callers turn it into their layer's error)."""


@dataclass(frozen=True)
class Member:
    """One array of an archive as its .npy header declares it (nothing of its data read)."""

    name: str  # the key (the zip member without .npy)
    shape: tuple[int, ...]
    dtype: np.dtype
    fortran_order: bool
    stored_bytes: int  # its size in the zip (compressed or not)

    @property
    def nbytes(self) -> int:
        return int(np.prod(self.shape, dtype=object)) * self.dtype.itemsize


def members(path: str | os.PathLike) -> dict[str, Member]:
    """Every array of the .npz at `path`, from the .npy headers alone; NpzError for anything else."""
    try:
        with zipfile.ZipFile(path) as zf:
            out = {}
            for info in zf.infolist():
                if not info.filename.endswith(".npy"):
                    continue
                with zf.open(info) as fp:
                    out[info.filename[:-4]] = _member(info, fp)
            return out
    except (zipfile.BadZipFile, OSError, EOFError, ValueError, SyntaxError, NotImplementedError) as exc:
        raise NpzError(str(exc) or type(exc).__name__) from None


def _read_header(fp) -> tuple:
    """(shape, fortran_order, dtype) of the .npy stream `fp`, left at its first data byte."""
    version = npy.read_magic(fp)
    read = {(1, 0): npy.read_array_header_1_0, (2, 0): npy.read_array_header_2_0}.get(version)
    if read is None:
        raise NpzError(f".npy format version {version} is not supported")
    return read(fp, max_header_size=MAX_HEADER)


def _member(info: zipfile.ZipInfo, fp) -> Member:
    shape, fortran, dtype = _read_header(fp)
    return Member(info.filename[:-4], tuple(int(x) for x in shape), np.dtype(dtype), bool(fortran), info.compress_size)


LIMIT_VARIABLE = "FLOCKCAL_MAX_TAKE_GB"
DEFAULT_LIMIT_GB = 4.0  # 4.9 hours of 16 sensors at 144 Hz (0.81 GB an hour), 2.5 times the service's longest session


def size_limit(limit_gb: float | None = None) -> int:
    """Bytes an archive's arrays may unpack to: `limit_gb`, else $FLOCKCAL_MAX_TAKE_GB, else 4 GB."""
    text = os.environ.get(LIMIT_VARIABLE, "").strip()
    where = "--max-take-gb" if limit_gb is not None else LIMIT_VARIABLE
    try:
        gb = float(limit_gb) if limit_gb is not None else float(text) if text else DEFAULT_LIMIT_GB
    except ValueError:
        gb = float("nan")
    if not gb > 0 or gb == float("inf"):
        raise NpzError(f"{where} must be a positive number of gigabytes, got {limit_gb if limit_gb is not None else text}")
    return int(gb * 1e9)


def available_memory() -> int | None:
    """Bytes of memory the machine can give a process now (MemAvailable), None where it cannot tell."""
    try:
        with open("/proc/meminfo", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def check_size(arrays: dict[str, Member], what: str, limit_gb: float | None = None, whole: bool = False) -> int:
    """The bytes `arrays` unpack to, once within the limit (and, `whole`: loading them needs at most twice
    that, within the memory available now); NpzError otherwise, naming `what` they hold."""
    declared = sum(a.nbytes for a in arrays.values())
    stored = sum(a.stored_bytes for a in arrays.values())
    limit = size_limit(limit_gb)
    holds = f"its arrays unpack to {_size(declared)} ({what}) from {_size(stored)} in the file"
    if declared > limit:
        raise NpzError(f"{holds} — more than the {_size(limit)} a take may unpack to (default {DEFAULT_LIMIT_GB:g} GB; "
                       f"--max-take-gb or {LIMIT_VARIABLE} give another limit)")
    free = available_memory() if whole else None
    if free is not None and 2 * declared > free:
        raise NpzError(f"{holds}; reading it whole needs up to {_size(2 * declared)} of memory and the machine has "
                       f"{_size(free)} available — free some memory, or use a command that reads takes a chunk at a "
                       f"time (flockcal fit, convert)")
    return declared


def _size(n: int) -> str:
    for unit, scale in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= scale:
            return f"{n / scale:.3g} {unit}"
    return f"{n} bytes"


class Reader:
    """An .npz open for reading its members whole (small ones) or a number of rows at a time (in order)."""

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self.members = members(self.path)
        try:
            self._zip = zipfile.ZipFile(self.path)
        except (zipfile.BadZipFile, OSError) as exc:
            raise NpzError(str(exc)) from None

    def whole(self, name: str) -> np.ndarray:
        try:
            with self._zip.open(name + ".npy") as fp:
                return npy.read_array(fp, allow_pickle=False)
        except (zipfile.BadZipFile, OSError, EOFError, ValueError) as exc:
            raise NpzError(f"{name}: {exc}") from None

    def rows(self, name: str) -> "RowStream | LoadedRows":
        """Member `name` a number of rows at a time: streamed from the zip, or (stored in Fortran order,
        which has no rows to stream) loaded whole first."""
        member = self.members[name]
        if member.fortran_order and len(member.shape) > 1:
            return LoadedRows(self.whole(name))
        return RowStream(self._zip, member)

    def close(self) -> None:
        self._zip.close()

    def __enter__(self) -> "Reader":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class RowStream:
    """One C-ordered member read along its first axis: `read(k)` gives the next k rows (fewer at the end)."""

    def __init__(self, zf: zipfile.ZipFile, member: Member):
        if member.dtype.hasobject:
            raise NpzError(f"{member.name}: holds Python objects, which a take never does")
        self.member = member
        self.row_shape = member.shape[1:]
        self.row_bytes = int(np.prod(self.row_shape, dtype=np.int64)) * member.dtype.itemsize
        self.left = member.shape[0] if member.shape else 0
        self._fp = zf.open(member.name + ".npy")
        _read_header(self._fp)

    def read(self, k: int) -> np.ndarray:
        k = max(0, min(int(k), self.left))
        want = k * self.row_bytes
        try:
            data = self._fp.read(want)
        except (zipfile.BadZipFile, OSError, EOFError) as exc:
            raise NpzError(f"{self.member.name}: {exc}") from None
        if len(data) != want:
            raise NpzError(f"{self.member.name}: its data ends before the {self.member.shape[0]} rows its header "
                           f"declares")
        self.left -= k
        return np.frombuffer(data, dtype=self.member.dtype).reshape((k,) + self.row_shape)

    def close(self) -> None:
        self._fp.close()


class Writer:
    """An .npz built a piece at a time: `append(name, rows)` adds rows to a member (its dtype and row shape
    fixed by the first call), `put(name, array)` a small array; `commit()` zips it all (deflated, as
    np.savez_compressed) into `path` atomically. The rows wait in raw files in a folder beside `path`
    (removed on commit or `discard()`), so memory holds one piece while the disk holds the arrays once."""

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self._dir = Path(tempfile.mkdtemp(prefix=f".{self.path.name}.", dir=self.path.parent or "."))
        self._rows: dict[str, tuple[np.dtype, tuple[int, ...], int, object]] = {}  # dtype, row shape, n, file
        self._small: dict[str, np.ndarray] = {}

    def append(self, name: str, rows: np.ndarray) -> None:
        rows = np.asarray(rows)
        if name not in self._rows:
            fh = open(self._dir / f"{len(self._rows)}.raw", "wb")
            self._rows[name] = (rows.dtype, rows.shape[1:], 0, fh)
        dtype, shape, n, fh = self._rows[name]
        if rows.shape[1:] != shape:
            raise ValueError(f"{name}: rows of shape {rows.shape[1:]} after rows of shape {shape}")
        fh.write(np.ascontiguousarray(rows, dtype=dtype).tobytes())
        self._rows[name] = (dtype, shape, n + len(rows), fh)

    def put(self, name: str, array) -> None:
        self._small[name] = np.asarray(array)

    def rows_of(self, name: str) -> int:
        return self._rows[name][2] if name in self._rows else 0

    def commit(self) -> None:
        try:
            with replacing(self.path) as tmp:
                with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_DEFLATED, allowZip64=True) as zf:
                    for name, (dtype, shape, n, fh) in self._rows.items():
                        fh.close()
                        header = {"descr": npy.dtype_to_descr(dtype), "fortran_order": False, "shape": (n,) + shape}
                        with zf.open(name + ".npy", "w", force_zip64=True) as out, open(fh.name, "rb") as raw:
                            npy.write_array_header_1_0(out, header)
                            shutil.copyfileobj(raw, out, COPY_BYTES)
                    for name, array in self._small.items():
                        with zf.open(name + ".npy", "w", force_zip64=True) as out:
                            npy.write_array(out, array, allow_pickle=False)
        finally:
            self.discard()

    def discard(self) -> None:
        for _dtype, _shape, _n, fh in self._rows.values():
            fh.close()
        shutil.rmtree(self._dir, ignore_errors=True)

    def __enter__(self) -> "Writer":
        return self

    def __exit__(self, *exc) -> None:
        self.discard()



class LoadedRows:
    """An array already in memory, handed out as RowStream hands out rows."""

    def __init__(self, array: np.ndarray):
        self.array, self.at = array, 0

    def read(self, k: int) -> np.ndarray:
        out = self.array[self.at:self.at + max(0, int(k))]
        self.at += len(out)
        return out

    def close(self) -> None:
        self.array = None
