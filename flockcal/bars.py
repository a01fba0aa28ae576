"""Progress bars for long command-line work (tqdm, on stderr).

A bar appears only when stdout and stderr are both terminals and the work has run for DELAY_S seconds,
so quick commands, pipes and redirected output stay quiet. $FLOCKCAL_PROGRESS_DELAY sets the delay
(seconds; 0 shows every bar at once).
"""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Sequence

DELAY_S = 2.0


def shown() -> bool:
    """Whether bars may be drawn: both output streams are a person's terminal."""
    try:
        return sys.stdout.isatty() and sys.stderr.isatty()
    except (AttributeError, ValueError):  # replaced or closed streams
        return False


def delay() -> float:
    try:
        return max(0.0, float(os.environ.get("FLOCKCAL_PROGRESS_DELAY", DELAY_S)))
    except ValueError:
        return DELAY_S


def bar(total: float | None, desc: str, unit: str = "it", unit_scale: bool = False):
    """A tqdm bar over `total` steps (update it with `.update(n)`; use it as a context manager); where
    none may be drawn, a stand-in that draws nothing."""
    if not shown():
        return _Quiet()
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit=unit, unit_scale=unit_scale, file=sys.stderr, leave=False,
                delay=delay())


class _Quiet:
    """What a bar is where none may be drawn: tqdm is not even imported (with the lock it makes on first
    use, 0.05–0.08 s of a CLI start: importlib.metadata, multiprocessing)."""

    disable = True

    def update(self, n: float = 1) -> None:
        pass

    def __enter__(self) -> "_Quiet":
        return self

    def __exit__(self, *exc) -> None:
        pass

    def set_postfix_str(self, s: str = "", refresh: bool = True) -> None:
        pass

    def close(self) -> None:
        pass


class Stages:
    """A bar over named stages of one job: `step(name)` finishes the previous stage and shows the next."""

    def __init__(self, desc: str, names: Sequence[str]):
        self.names = list(names)
        self._bar = bar(len(self.names), desc, unit="step") if shown() else _Quiet()
        self._started = False
        self._shown_after = time.monotonic() + delay()

    def step(self, name: str) -> None:
        if self._started:
            self._bar.update(1)
        self._started = True
        # Redrawn at once only once the bar is due: a job done within the delay stays silent.
        self._bar.set_postfix_str(name, refresh=time.monotonic() >= self._shown_after)

    def close(self) -> None:
        self._bar.close()

    def __enter__(self) -> "Stages":
        return self

    def __exit__(self, *exc) -> None:
        if exc[0] is None and self._started:
            self._bar.update(1)
        self.close()
