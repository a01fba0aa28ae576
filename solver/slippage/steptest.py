"""The slippage monitor's step test: each joint's lagged smooth baseline, the deviations from it with their
noise weights, and the window GLR test for a step in them that raises a suspicion (docs/slippage.md).
"""

from __future__ import annotations

import numpy as np

from flockcal.solver.slippage.baseline import SmoothBaseline, smooth_baseline
from flockcal.solver.slippage.stats import best_step, glr_candidates, local_variance, residual


class StepTest:
    """`SlipMonitor`'s step test, on the monitor's frame buffer (`_buf`), joints and settings: `_refresh` fits
    every joint's baseline over the lagged window, `_deviations` works out the frames against it, and
    `_candidates`/`_scan` score a step at each step's last frame. Its state: the baseline and the
    estimates it was fitted with, which joints are watched (`ready`), their rms and latest scores."""

    def _init_step_test(self, p: int) -> None:
        s, rate_hz = self.settings, self.rate_hz
        self.window = max(2, int(round(s.window_s * rate_hz)))
        self.noise_frames = max(5, int(round(s.noise_s * rate_hz)))
        self._baseline_frames = int(round(s.baseline_s * rate_hz))
        # Frames kept by the fits, evenly spread over their window: the smooth part needs no more.
        self._fit_rows = 300
        self.ready = np.zeros(p, dtype=bool)
        self.rms = np.full(p, np.nan)  # each joint's residual rms over its baseline window, metres
        self.base: SmoothBaseline | None = None
        self._c_ref = np.full((p, 3), np.nan)
        self._l_ref = np.full((p, 3), np.nan)
        self._last_refresh = -np.inf
        self._fresh: tuple[int, int] | None = None  # global frames whose buf.dx/dy/w follow the current baseline
        self.score = np.zeros(p)  # latest GLR score per joint (nats), for display

    def _refresh(self, now: float, c, l) -> None:
        """Recompute every joint's baseline with the current estimates from the lagged window."""
        buf = self._buf
        sl = buf.between(now - self.settings.lag_s - self.settings.baseline_s, now - self.settings.lag_s)
        stride = max(1, (sl.stop - sl.start) // self._fit_rows)
        Q = buf.Q[sl]
        mask = buf.pv[sl] & (buf.times[sl][:, None] >= self.segment_start[None, :])
        u, Qs, ms = residual(buf.g[sl][::stride], Q[::stride], c, l), Q[::stride], mask[::stride]
        self.base = smooth_baseline(u, Qs, ms, self._nbrs, self.settings.scale_floor_m)
        self.base.frames = mask.sum(axis=0)
        with np.errstate(invalid="ignore"):
            self.rms = np.sqrt(np.where(ms, (u * u).sum(axis=-1), 0.0).sum(axis=0) / ms.sum(axis=0))
        enough = self.base.frames >= 0.6 * min(self.settings.warmup_s, self.settings.baseline_s) * self.rate_hz
        settled = now - self.segment_start >= max(self.settings.warmup_s, self.settings.lag_s)
        # A joint's residual is tracker noise and soft tissue, a couple of centimetres at most; a pair
        # whose residual is larger than max_rms_m is two bodies that are not joined (an object in the
        # hand, a wrong tree edge): steps in it are no slips, and it is not watched.
        joined = self.rms <= self.settings.max_rms_m
        self.ready = enough & settled & np.isfinite(self.base.sigma) & joined
        self._c_ref, self._l_ref = np.array(c, dtype=float), np.array(l, dtype=float)
        self._last_refresh = now
        self._fresh = None  # every deviation must be worked out again against the new baseline

    def _deviations(self, first: int, c, l) -> None:
        """Bring the buffer's deviations and noise weights up to date from global frame `first` on.
        Only frames not yet worked out against the current baseline are (the others cannot change: the
        baseline follows new estimates exactly), with the noise window they need behind them."""
        buf = self._buf
        end = buf.index_of(buf.hi)
        if self._fresh is None or self._fresh[0] > first:
            new_from, var_from = first, first
        else:
            new_from = self._fresh[1]
            var_from = max(self._fresh[0], new_from - self.noise_frames - 1)
        if new_from >= end:
            return
        sl, rows = buf.since(new_from), buf.since(var_from)
        Q = buf.Q[sl]
        buf.dx[sl], buf.dy[sl] = self.base.deviations(residual(buf.g[sl], Q, c, l), Q)
        var = local_variance(buf.dx[rows], buf.pv[rows], self.noise_frames)[sl.start - rows.start:]
        sigma2 = np.nan_to_num(self.base.sigma, nan=0.0) ** 2
        floor = np.maximum(0.25 * sigma2, self.settings.scale_floor_m**2)
        ok = np.isfinite(var)
        var = np.maximum(np.where(ok, var, 1.0), floor)
        # Where the configuration is new the baseline extrapolates: the step test, which measures against
        # it, counts its uncertainty as noise. The confirming test fits its own smooth function over the
        # window; for a sensor seen through two or more joints, which a slip moves by one vector in its own
        # frame while skin in a new pose moves each joint its own way, it may count less of it
        # (`extrapolation_share`). By default it counts all of it: counting none raised false alarms in
        # fresh kiosk guests, for leaves and for sensors of two joints alike (docs/slippage.md).
        extra = sigma2 * self.base.leverage(Q)
        live = buf.pv[sl] & ok
        step_share, joined_share = self.settings.shares[:2]
        buf.w[sl] = np.where(live, 1.0 / (var + step_share * extra), 0.0)
        buf.nv[sl] = np.where(live, var, 0.0)
        if joined_share != step_share:
            buf.wc[sl] = np.where(live, 1.0 / (var + joined_share * extra), 0.0)
        self._fresh = (min(first, new_from) if self._fresh is None else min(self._fresh[0], new_from), end)

    def _candidates(self, first: int, lasts: list[int]):
        """The step test's evidence at the last frames `lasts` of a block's steps, for every candidate start
        (`glr_candidates`): the block's deviations stay as they are while its steps are tested, so one
        computation serves every round of them; `_scan` picks each round's best."""
        buf = self._buf
        sl = slice(buf.slot(first), buf.slot(lasts[-1]) + 1)
        first_row = buf.index_of(sl.start)
        xs = np.concatenate([buf.dx[sl], buf.dy[sl]], axis=1)  # child-frame and parent-frame series side by side
        w = buf.w[sl]
        ws = np.concatenate([w, w], axis=1)
        # One end per step, its last frame: a step that stays only gains evidence with time.
        g, usable, tau = glr_candidates(xs, ws, np.asarray(lasts) - first_row, self.window, 0.5 * self.settings.min_jump_m,
                                        self.settings.min_frames)
        return g, usable, tau, first_row

    def _scan(self, candidates, j: int, ready):
        """The step test at the block's steps from the j-th on: scores and starts (steps, p)."""
        g, usable, tau, first_row = candidates
        earliest = np.maximum(self._quiet, 0) - first_row
        score, start = best_step(g[j:], usable[j:], tau[j:], np.concatenate([earliest, earliest]))
        p = len(self.joints)
        which = score[:, p:] > score[:, :p]
        score = np.where(which, score[:, p:], score[:, :p])
        start = np.where(which, start[:, p:], start[:, :p])
        return np.where(ready[None, :], score, 0.0), start, first_row
