"""Fits for the live service: the fit worker thread and the one place a fit is made. A fit travels as its
typed `Calibration` (what the session's live calibration computes with, solver/live.py; what the store keeps
whole, server/store.py); its §5 dict is made at the edge, once, when a client asks for it (`FitView.doc`).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass
from functools import cached_property
from typing import Callable

import numpy as np

from flockcal.errors import FlockcalError
from flockcal.solver.calibration import Calibration
from flockcal.solver.humanoid import Humanoid, Sample
from flockcal.solver.solve import solve
from flockcal.threads import name_os_thread

log = logging.getLogger(__name__)

def json_safe(obj):
    """JSON-safe copy: NaN and ±inf become None (browsers cannot parse them), numpy scalars become floats."""
    kind = type(obj)
    if kind is float:  # the common leaves first, by exact type: most of the cost is the walk itself
        return obj if math.isfinite(obj) else None
    if kind is str or kind is int or kind is bool or obj is None:
        return obj
    if isinstance(obj, dict):
        return {k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(obj) else None
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    return obj


def solve_fit(acc, names, hierarchy=None, root=None, skeleton=None, tolerance: float = 0.005,
              previous: Calibration | None = None, sample: Sample | None = None,
              humanoid: Humanoid | None = None) -> Calibration:
    """A fit of `acc`: the solver's `solve` picks plain, slip-segmented or saved-skeleton fitting; `previous`
    (the session's last fit) warm-starts a saved-skeleton fit; the humanoid is found from `sample`, the last
    one (`humanoid`, else `previous`'s) kept while the tree and the sample have not changed enough to matter.
    SolverError etc. propagate."""
    if skeleton is not None:
        return solve(acc, names, skeleton=skeleton, previous=previous, sample=sample, humanoid=humanoid)
    return solve(acc, names, hierarchy, root, tolerance=tolerance, previous=previous, sample=sample, humanoid=humanoid)


def fit_doc(cal: Calibration) -> dict:
    """The JSON-safe §5 dict of a fit. The solver builds a fitted tree's dict JSON-safe (Python scalars,
    None for NaN; the tests hold it to that), so only a saved skeleton's is walked again."""
    return json_safe(cal.to_dict()) if cal.known_skeleton else cal.to_dict()


def fit_calibration(acc, names, hierarchy=None, root=None, skeleton=None, tolerance: float = 0.005,
                    previous: Calibration | None = None, sample: Sample | None = None,
                    humanoid: Humanoid | None = None) -> tuple[dict, Calibration]:
    """(JSON-safe §5 dict, Calibration) of `solve_fit`: a session's final fit, which is stored."""
    cal = solve_fit(acc, names, hierarchy, root, skeleton, tolerance, previous, sample, humanoid)
    return fit_doc(cal), cal


class FitView:
    """A live fit as the snapshots carry it: the typed `Calibration`, and its §5 dict made on first use (by
    a client's `fit` message or the REST result), once for every snapshot that shows this fit. The fit
    thread makes ~30 fits a second; a dashboard takes at most 15 of them."""

    def __init__(self, calibration: Calibration):
        self.calibration = calibration

    @cached_property
    def doc(self) -> dict:
        return fit_doc(self.calibration)


@dataclass(frozen=True)
class FitJob:
    session_id: str
    acc: object  # a copy the fit thread owns; the live accumulator keeps growing
    hierarchy: object
    root: str | None
    skeleton: object
    stamp: tuple[float, int]  # (session time, slip epoch) the fit was begun at
    tolerance: float | None = None  # the session's (its profile's); None: the worker's own
    sample: Sample | None = None  # the session's sample of frames, to find the humanoid from
    previous: Calibration | None = None  # the session's newest fit (its humanoid is kept while it holds)


@dataclass(frozen=True)
class FitDone:
    session_id: str
    calibration: Calibration | None  # None when the fit failed (`error` says why)
    error: str | None
    seconds: float
    stamp: tuple[float, int]


class FitWorker:
    """Refits on its own thread ("fc-fit"), so a slow fit never delays frames or snapshots.

    Threads: `submit`, `take`, `start` and `stop` are called by the pipeline thread; `_run` is the fit
    thread. The one condition variable `_cond` guards every field the two threads share (`_job`, `_done`,
    `_busy`, `_stop`): nothing reads or writes them without it. The warm start of saved-skeleton fits
    (`_known_prev`) belongs to the fit thread alone. `on_done` runs on the fit thread after the lock is
    released (so it may take the pipeline's lock: the order is always pipeline lock → this one, never back).
    """

    def __init__(self, names, tolerance: float, on_done: Callable[[], None] = lambda: None):
        self.names = tuple(names)
        self.tolerance = float(tolerance)
        self.on_done = on_done
        self._cond = threading.Condition()
        self._job: FitJob | None = None
        self._done: FitDone | None = None
        self._busy = False  # a job is queued or being fitted
        self._stop = False
        self._thread: threading.Thread | None = None
        self._known_prev = None  # (session id, KnownFit)
        self.fits_done = 0  # results taken, and the seconds they took (pipeline thread: `take`)
        self.fit_seconds = 0.0

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="flockcal-fit", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        with self._cond:
            self._stop = True
            self._cond.notify()
        if self._thread:
            self._thread.join(10)

    def submit(self, job: FitJob) -> bool:
        """Queue a fit unless one is queued or running; False if busy (the caller tries again later)."""
        with self._cond:
            if self._busy:
                return False
            self._busy = True
            self._job = job
            self._cond.notify()
            return True

    @property
    def busy(self) -> bool:
        with self._cond:
            return self._busy

    def has_result(self) -> bool:
        with self._cond:
            return self._done is not None

    def take(self) -> FitDone | None:
        """The newest finished fit, once."""
        with self._cond:
            done, self._done = self._done, None
        if done is not None:
            self.fits_done += 1
            self.fit_seconds += done.seconds
        return done

    def _run(self) -> None:
        name_os_thread("fc-fit")
        while True:
            with self._cond:
                while self._job is None and not self._stop:
                    self._cond.wait()
                if self._stop:
                    return
                job, self._job = self._job, None
            start = time.perf_counter()
            cal, error = None, None
            try:
                cal = self._fit(job)
            except FlockcalError as exc:
                error = str(exc)
            except Exception as exc:  # a numerical failure must not stop the service
                log.exception("fit failed")
                error = f"fit failed: {exc}"
            with self._cond:
                self._done = FitDone(job.session_id, cal, error, time.perf_counter() - start, job.stamp)
                self._busy = False
            self.on_done()

    def _fit(self, job: FitJob) -> Calibration:
        if job.skeleton is None:
            tolerance = self.tolerance if job.tolerance is None else job.tolerance
            return solve_fit(job.acc, self.names, job.hierarchy, job.root, tolerance=tolerance, previous=job.previous,
                             sample=job.sample)
        # Start from this session's last known-skeleton fit: one or two Gauss–Newton steps.
        prev = self._known_prev[1] if self._known_prev and self._known_prev[0] == job.session_id else None
        known = solve_fit(job.acc, self.names, skeleton=job.skeleton, previous=prev, sample=job.sample)
        self._known_prev = (job.session_id, known)
        return known
