"""Writing files so that a crash never leaves half of one under its name: write beside, then rename.

Used for every file flockcal writes whole (takes, BVH, skeletons, reports, truth files). A file that
cannot be written is an `OutputError` naming it and the fix, with nothing left behind.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path

from flockcal.errors import FlockcalError


class OutputError(FlockcalError, OSError):
    """A file that cannot be written where it was asked for (an OSError too, for callers that catch those)."""


def check_output(path: str | os.PathLike, option: str = "-o") -> Path:
    """`path` as a Path once its folder exists and `path` is not a folder itself; else an OutputError
    naming `option`, the path and the fix. Commands call it before their work, so a long fit does not
    end in this error."""
    p = Path(path)
    folder = p.parent
    if p.is_dir():
        raise OutputError(f"{option} {p}: that is a folder; give a file name inside it")
    if not folder.is_dir():
        what = "is not a folder" if folder.exists() else "does not exist"
        raise OutputError(f"{option} {p}: the folder {folder} {what}; create it (mkdir -p {folder}) or write "
                          f"elsewhere")
    return p


def _discard(tmp: Path) -> None:
    try:
        tmp.unlink(missing_ok=True)
    except OSError:  # the folder went away or is read-only: there is nothing to clean up then
        pass


@contextmanager
def replacing(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside `path`; once the block finishes, it replaces `path` in one rename.

    The block only writes the temporary file: an OSError in it (no such folder, no permission, disk
    full) becomes an OutputError naming `path`. On any error or interrupt the temporary file is removed
    and `path` keeps what it held before."""
    path = Path(path)
    tmp = path.with_name(path.name + ".part")
    try:
        yield tmp
        os.replace(tmp, path)
    except OutputError:
        _discard(tmp)
        raise
    except OSError as exc:
        _discard(tmp)
        why = exc.strerror or str(exc)
        raise OutputError(f"cannot write {path}: {why}; check that its folder exists and is writable, or write "
                          f"elsewhere") from None
    except BaseException:
        _discard(tmp)
        raise


def write_atomic(path: str | os.PathLike, data: str | bytes, encoding: str = "utf-8") -> None:
    """Write text or bytes to `path` atomically."""
    with replacing(path) as tmp:
        tmp.write_bytes(data.encode(encoding) if isinstance(data, str) else data)


def write_pieces(path: str | os.PathLike, pieces: Iterable[str | bytes], encoding: str = "utf-8") -> None:
    """Write text or bytes that come a piece at a time (a long take's export) to `path` atomically: memory
    holds one piece, and a failure part way leaves `path` as it was."""
    with replacing(path) as tmp, open(tmp, "wb") as fh:
        for piece in pieces:
            fh.write(piece.encode(encoding) if isinstance(piece, str) else piece)
