"""Writing files so that a crash never leaves half of one under its name: write beside, then rename.

Used for every file flockcal writes whole (takes, BVH, skeletons, reports, truth files).
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


@contextmanager
def replacing(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside `path`; once the block finishes, it replaces `path` in one rename."""
    path = Path(path)
    tmp = path.with_name(path.name + ".part")
    yield tmp
    os.replace(tmp, path)


def write_atomic(path: str | os.PathLike, data: str | bytes, encoding: str = "utf-8") -> None:
    """Write text or bytes to `path` atomically."""
    with replacing(path) as tmp:
        tmp.write_bytes(data.encode(encoding) if isinstance(data, str) else data)
