"""Operating-system names for flockcal's worker threads, so `top -H` and /proc/PID/task/*/comm tell them apart.

The benchmarks read per-thread CPU by these names; an operator sees which stage is busy.
"""

from __future__ import annotations

import ctypes
import sys

_PR_SET_NAME = 15


def name_os_thread(name: str) -> None:
    """Give the calling thread an OS-level name (15 bytes at most; Linux only, a no-op elsewhere)."""
    if not sys.platform.startswith("linux"):
        return
    try:
        ctypes.CDLL(None).prctl(_PR_SET_NAME, name.encode()[:15], 0, 0, 0)
    except (OSError, AttributeError):
        pass
