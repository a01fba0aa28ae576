"""Checks on decoded cycles that need each bird's past: motion continuity of suspect records, hemisphere
unfolding, and position saturation reports.

`BirdChecks` keeps the per-bird memory across batches; the FrameAssembler that owns it calls `apply`
on each batch, on its own thread, in stream order (so replay reaches the same decisions).
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from flockcal.drivers.link import FlockSetup

_POSITION_FORMATS = ("position", "position_angles", "position_matrix", "position_quaternion")


class BirdChecks:
    """Per-bird memory (last valid pose and its time, last raw position, hemisphere parity) and the
    checks that use it. `emit((kind, message, data))` receives the events (flips, saturation)."""

    def __init__(self, setup: FlockSetup, emit: Callable[[tuple[str, str, dict]], None], *,
                 hemisphere_tracking: bool = True, max_speed: float = 20.0, max_turn_rate: float = 60.0,
                 saturation_quiet: float = 1.0):
        self.setup = setup
        self.m = setup.birds
        self.emit = emit
        self.hemisphere_tracking = hemisphere_tracking and setup.record_format in _POSITION_FORMATS
        self.max_speed = max_speed
        self.max_turn_rate = max_turn_rate
        self.saturation_quiet = saturation_quiet
        self.last_time = np.full(self.m, -np.inf)
        self.last_pos = np.full((self.m, 3), np.nan)
        self.last_rot = np.full((self.m, 3, 3), np.nan)
        self.raw_last = np.full((self.m, 3), np.nan)  # last raw (folded) position, for the flip test
        self.flipped = np.zeros(self.m, bool)
        self.saturated_records = 0  # bird-frames whose position was clipped at full scale
        self.last_saturated = -np.inf  # time of the last frame with a clipped position

    def apply(self, cycle_times, R, p, valid, suspect, rec_time, clipped) -> int:
        """Check one batch of cycles (n, m) in place: invalidates implausible suspect records, unfolds
        hemisphere flips in `p`, reports clipping (`clipped` None when there is none). Returns the number
        of records rejected."""
        if clipped is not None:
            self._report_saturation(cycle_times, clipped)
        rejected = self._check_suspects(R, p, valid, suspect, rec_time) if suspect.any() else 0
        if self.hemisphere_tracking:
            self._track_hemisphere(p, valid)
        self._remember(R, p, valid, rec_time)
        return rejected

    def _report_saturation(self, cycle_times: np.ndarray, clipped: np.ndarray) -> None:
        """Count clipped positions; one event per burst (clipping after `saturation_quiet` s without)."""
        self.saturated_records += int(np.count_nonzero(clipped))
        rows = np.flatnonzero(clipped.any(axis=1))
        t = cycle_times[rows]
        before = np.concatenate([[self.last_saturated], t[:-1]])
        scale = self.setup.scale_inches
        if scale < 72:
            fix = "use the 72-inch scale (--scale 72) or move the transmitter closer to the performance area"
        else:
            fix = f"{scale:g} in is the largest scale: move the transmitter closer to the performance area"
        for row in rows[t - before > self.saturation_quiet]:
            birds = [int(b) for b in np.flatnonzero(clipped[row])]
            self.emit(("position_saturated",
                                f"bird(s) {', '.join(map(str, birds))} beyond the {scale:g}-inch position full "
                                f"scale: clipped positions are marked invalid — {fix}",
                                {"birds": birds, "scale_inches": float(scale)}))
        self.last_saturated = max(self.last_saturated, float(t[-1]))

    def _check_suspects(self, R, p, valid, suspect, rec_time) -> int:
        """Keep a suspect record only if it continues the bird's motion (a garbled one jumps far away);
        returns how many were rejected."""
        rejected = 0
        for f, b in zip(*np.nonzero(suspect)):  # rare: only records next to lost bytes
            prev = np.flatnonzero(valid[:f, b])
            if len(prev):
                q, Q, tq = p[prev[-1], b], R[prev[-1], b], rec_time[prev[-1], b]
            else:
                q, Q, tq = self.last_pos[b], self.last_rot[b], self.last_time[b]
            dt = rec_time[f, b] - tq
            keep = False
            if np.isfinite(dt) and dt <= 0.5:
                dt = max(dt, 1.0 / max(self.setup.rate_hz, 1.0))
                keep = True
                if np.all(np.isfinite(p[f, b])) and np.all(np.isfinite(q)):
                    # Mirror-tolerant: a hemisphere crossing flips the reported position.
                    jump = min(np.linalg.norm(p[f, b] - q), np.linalg.norm(p[f, b] + q))
                    keep &= jump <= self.max_speed * dt + 0.03
                if np.all(np.isfinite(R[f, b])) and np.all(np.isfinite(Q)):
                    cos = (np.trace(Q.T @ R[f, b]) - 1.0) / 2.0
                    keep &= np.arccos(np.clip(cos, -1.0, 1.0)) <= self.max_turn_rate * dt + 0.2
            if not keep:
                valid[f, b] = False
                rejected += 1
        return rejected

    def _track_hemisphere(self, p: np.ndarray, valid: np.ndarray) -> None:
        """Undo hemisphere folding: the bird reports −p once a sensor crosses into the other hemisphere.

        Consecutive valid raw positions pointing to opposite sides (p·q < 0) can only be such a flip (a
        real move would have to pass through the transmitter). Positions are corrected in place.
        """
        n = len(p)
        if valid.all():  # the usual case: each bird's previous position is the row above
            prev = np.concatenate([self.raw_last[None], p[:-1]])
            raw_last = p[-1].copy()
        else:
            rows = np.arange(n)[:, None]
            idx = np.where(valid, rows, -1)
            last = np.maximum.accumulate(idx, axis=0)
            prev_idx = np.vstack([np.full((1, self.m), -1), last[:-1]])
            cols = np.arange(self.m)[None, :]
            prev = np.where((prev_idx >= 0)[..., None], p[np.maximum(prev_idx, 0), cols], self.raw_last)
            raw_last = np.where((last[-1] >= 0)[:, None], p[np.maximum(last[-1], 0), np.arange(self.m)],
                                self.raw_last)
        toggle = valid & (np.einsum("nmi,nmi->nm", p, prev) < 0)
        if toggle.any():
            for b in np.flatnonzero(toggle.any(axis=0)):
                self.emit(("hemisphere_flip", f"bird {b} crossed the hemisphere boundary "
                                    f"{int(toggle[:, b].sum())} time(s); positions corrected",
                                    {"bird": int(b), "count": int(toggle[:, b].sum())}))
        self.raw_last = raw_last
        if not toggle.any():
            if self.flipped.any():
                p[:, self.flipped] *= -1.0
            return
        parity = (np.cumsum(toggle, axis=0) + self.flipped[None, :]) % 2 == 1
        self.flipped = parity[-1].copy()
        p[parity] *= -1.0

    def _remember(self, R, p, valid, rec_time) -> None:
        if valid[-1].all():
            self.last_pos[:] = p[-1]
            self.last_rot[:] = R[-1]
            self.last_time[:] = rec_time[-1]
            return
        seen = valid.any(axis=0)
        if not seen.any():
            return
        last = len(valid) - 1 - np.argmax(valid[::-1], axis=0)
        b = np.flatnonzero(seen)
        self.last_pos[b] = p[last[b], b]
        self.last_rot[b] = R[last[b], b]
        self.last_time[b] = rec_time[last[b], b]
