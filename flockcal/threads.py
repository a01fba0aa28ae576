"""Threads: operating-system names for flockcal's worker threads, so `top -H` and /proc/PID/task/*/comm
tell them apart (the benchmarks read per-thread CPU by these names), and keeping BLAS to one thread.
"""

from __future__ import annotations

import ctypes
import os
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


def single_threaded_blas() -> None:
    """Ask numpy's BLAS for one thread, unless the user chose otherwise; only works before numpy loads.

    flockcal's products are small (64×64 Grams, a few hundred frames at a time): a second BLAS thread
    speeds none of them up, and its spin-waiting doubled the slip scan's CPU time on a loaded machine.
    """
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")
