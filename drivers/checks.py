"""Checks on decoded cycles that need each bird's past: motion continuity of suspect records, hemisphere
unfolding, and position saturation reports.

`BirdChecks` keeps the per-bird memory across batches; the FrameAssembler that owns it calls `apply`
on each batch, on its own thread, in stream order (so replay reaches the same decisions).
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from flockcal.drivers.link import FlockSetup
from flockcal.hemisphere_unfold import HemisphereUnfold, path_toggles

_POSITION_FORMATS = ("position", "position_angles", "position_matrix", "position_quaternion")

# A record read next to lost or garbled bytes (a suspect) is kept only if it continues the bird's motion from
# its last valid record and also lies on the way to its next trusted record (one not next to lost bytes):
# line noise can forge a well-formed record whose x alone is wrong by 28 cm, which continues well enough
# (14 m/s at 50 Hz, under the 20 m/s a limb may reach) but does not return. The way is the straight line
# between the two neighbours, give or take what an acceleration of MAX_ACCEL_M_S2 bends a path in that time
# (A/2 · t_before · t_after) plus PATH_NOISE_M; for orientation the detour Q→R→next beyond Q→next, likewise.
# At 50 Hz with both neighbours one frame away: 2 + 2 cm.
MAX_ACCEL_M_S2 = 100.0  # 10 g: a fast strike of the arm (a 30 cm swing at 3 Hz peaks at 107 m/s² … only there)
MAX_ANGULAR_ACCEL = 1000.0  # rad/s²
PATH_NOISE_M = 0.02  # the tracker's noise far from the transmitter and at speed, with a margin
PATH_NOISE_RAD = 0.2
JUMP_NOISE_M, JUMP_NOISE_RAD = 0.03, 0.2  # the continuity test's allowance beyond max speed and turn rate
CONFIRM_S = 0.25  # a suspect whose bird sends no trusted record this soon after is dropped


def _angle(A: np.ndarray, B: np.ndarray) -> float:
    return float(np.arccos(np.clip((np.trace(A.T @ B) - 1.0) / 2.0, -1.0, 1.0)))


# A bird's first record is placed by the other birds of its frame only when there are more than this many:
# one frame's distances among fewer say little (the take's own rule, flockcal/hemisphere_unfold.py, has
# every frame of a stretch to go on).
PLACE_MIN_OTHERS = 3


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
        self._all_seen = False  # every bird has had a record (`_place_first_seen` has placed them all)
        self.saturated_records = 0  # bird-frames whose position was clipped at full scale
        self.last_saturated = -np.inf  # time of the last frame with a clipped position

    def apply(self, cycle_times, R, p, valid, rec_time, clipped, words=None) -> None:
        """Finish one batch of cycles (n, m) whose suspects `decide_suspects` has decided, in place: unfolds
        hemisphere flips in `p` (and in the position words of `words` (n, m, k), the data words the poses
        came from, so that they stay the words of the corrected positions), reports clipping (`clipped` None
        when there is none)."""
        if clipped is not None:
            self._report_saturation(cycle_times, clipped)
        if self.hemisphere_tracking:
            self._track_hemisphere(p, valid, words)
        self._remember(R, p, valid, rec_time)

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

    def decide_suspects(self, cycle_times, R, p, valid, suspect, rec_time, final: bool) -> tuple[int, int]:
        """Keep or drop (valid False) each suspect record that can be decided now, in stream order, and clear
        its `suspect` flag. One whose bird's next trusted record has not arrived, with less than CONFIRM_S of
        cycles after it, cannot be decided yet (unless `final`: the stream ended). Returns (rows from the start
        with nothing left undecided, records dropped): the caller holds the rest back for the next batch."""
        rejected = 0
        trusted = valid & ~suspect
        period = 1.0 / max(self.setup.rate_hz, 1.0)
        for f, b in zip(*np.nonzero(suspect)):  # rare: only records next to lost bytes; row by row
            later = np.flatnonzero(trusted[f + 1:, b])
            g = f + 1 + int(later[0]) if len(later) else None
            if g is not None and cycle_times[g] - cycle_times[f] > CONFIRM_S:
                g = None
            if g is None and not final and cycle_times[-1] - cycle_times[f] <= CONFIRM_S:
                return int(f), rejected  # wait for the bird's next record
            prev = np.flatnonzero(valid[:f, b])
            if len(prev):
                q, Q, tq = p[prev[-1], b], R[prev[-1], b], rec_time[prev[-1], b]
            else:
                q, Q, tq = self.last_pos[b], self.last_rot[b], self.last_time[b]
            keep = g is not None and self._continues(p[f, b], R[f, b], rec_time[f, b], q, Q, tq, period)
            if keep:
                keep = self._on_the_way(p[f, b], R[f, b], rec_time[f, b], q, Q, tq,
                                        p[g, b], R[g, b], rec_time[g, b], period)
            suspect[f, b] = False
            if not keep:
                valid[f, b] = False
                rejected += 1
        return len(cycle_times), rejected

    def _continues(self, x, X, t, q, Q, tq, period: float) -> bool:
        """The record (x, X at t) is within reach of the bird's last valid one (q, Q at tq)."""
        dt = t - tq
        if not (np.isfinite(dt) and dt <= 0.5):
            return False
        dt = max(dt, period)
        if np.all(np.isfinite(x)) and np.all(np.isfinite(q)):
            # Mirror-tolerant: a hemisphere crossing flips the reported position.
            jump = min(np.linalg.norm(x - q), np.linalg.norm(x + q))
            if jump > self.max_speed * dt + JUMP_NOISE_M:
                return False
        if np.all(np.isfinite(X)) and np.all(np.isfinite(Q)) and _angle(Q, X) > self.max_turn_rate * dt + JUMP_NOISE_RAD:
            return False
        return True

    @staticmethod
    def _on_the_way(x, X, t, q, Q, tq, r, Rn, tr, period: float) -> bool:
        """The record lies on the way from the last valid record (q at tq) to the next trusted one (r at tr):
        a one-record excursion that returns is line noise, not motion."""
        before, after = max(t - tq, period), max(tr - t, period)
        if not (np.isfinite(before) and np.all(np.isfinite(q)) and np.all(np.isfinite(x))):
            return True  # no previous pose to judge by: the continuity test decided
        # Hemisphere-tolerant: flip the later positions to the side of q.
        r = r if np.linalg.norm(r - q) <= np.linalg.norm(r + q) else -r
        x = x if np.linalg.norm(x - q) <= np.linalg.norm(x + q) else -x
        expected = q + (r - q) * (before / (before + after))
        if np.linalg.norm(x - expected) > 0.5 * MAX_ACCEL_M_S2 * before * after + PATH_NOISE_M:
            return False
        if np.all(np.isfinite(Q)) and np.all(np.isfinite(X)) and np.all(np.isfinite(Rn)):
            detour = _angle(Q, X) + _angle(X, Rn) - _angle(Q, Rn)
            if detour > MAX_ANGULAR_ACCEL * before * after + PATH_NOISE_RAD:
                return False
        return True

    def _track_hemisphere(self, p: np.ndarray, valid: np.ndarray, words: np.ndarray | None = None) -> None:
        """Undo hemisphere folding: the bird reports −p once a sensor crosses into the other hemisphere.

        Consecutive valid raw positions pointing to opposite sides (p·q < 0) can only be such a flip (a
        real move would have to pass through the transmitter: `path_toggles`, which files are unfolded
        with too). Positions are corrected in place.
        """
        self._place_first_seen(p, valid)
        toggle, self.raw_last = path_toggles(p, valid, self.raw_last)
        if toggle.any():
            for b in np.flatnonzero(toggle.any(axis=0)):
                self.emit(("hemisphere_flip", f"bird {b} crossed the hemisphere boundary "
                                    f"{int(toggle[:, b].sum())} time(s); positions corrected",
                                    {"bird": int(b), "count": int(toggle[:, b].sum())}))
        if not toggle.any():
            if self.flipped.any():
                # 0 − p, not −p: a zero coordinate stays +0.0, as the negated word (0) decodes
                p[:, self.flipped] = 0.0 - p[:, self.flipped]
                if words is not None:  # the words of the corrected positions, decoding to them bit for bit
                    words[:, self.flipped, :3] *= -1
            return
        parity = (np.cumsum(toggle, axis=0) + self.flipped[None, :]) % 2 == 1
        self.flipped = parity[-1].copy()
        p[parity] = 0.0 - p[parity]
        if words is not None:
            words[parity, :3] *= -1

    def _place_first_seen(self, p: np.ndarray, valid: np.ndarray) -> None:
        """A bird's first record since the reader started (a service started while the performer moves) may
        come from the other hemisphere, and toggles are tracked from there on: its sign is set once, by the
        rule that places a take's new stretches (`HemisphereUnfold`, on the one frame it first appears in):
        where the birds already placed are, strongest pair first; birds that all appear together (the
        connection's first frame) are placed among themselves, and if that shows a flip, which of the two
        mirror images of the whole performer is real is the take rule's convention (in front of the
        transmitter, else inside the configured hemisphere), not whichever most birds happen to read."""
        if self._all_seen:  # every bird placed: nothing to look at on the reader's hand-overs from here on
            return
        unseen = np.isnan(self.raw_last[:, 0])
        self._all_seen = not (unseen & ~valid.any(axis=0)).any()
        new = unseen & valid.any(axis=0)
        if not new.any():
            return
        first = np.argmax(valid, axis=0)
        placed = ~unseen
        for r in sorted(set(first[new].tolist())):  # the rows birds first appear in: nearly always one
            birds = new & (first == r)
            here = valid[r] & (birds | placed)
            if here.sum() > PLACE_MIN_OTHERS:
                x = np.where((self.flipped & placed)[:, None], -p[r], p[r])  # placed birds as corrected
                unfold = HemisphereUnfold(self.m, self.setup.hemisphere)
                known = here & placed
                unfold.placed[known] = True  # carried: placed from the start, never mirrored themselves
                unfold.last_time[known] = 0.0
                unfold.last_raw[known] = x[known]
                unfold.feed(np.zeros(1), x[None], here[None])
                for b in np.flatnonzero(unfold.started_mirrored & birds):
                    self.flipped[b] = True
                    self.emit(("hemisphere_flip", f"bird {b} began across the hemisphere boundary (its mirror "
                                                  "image is where the other sensors place it); positions "
                                                  "corrected", {"bird": int(b), "count": 1}))
            placed = placed | birds

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
