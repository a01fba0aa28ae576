"""The slippage monitor's frame-rate step test: every sensor with a ready joint scored for a step at every
onset (`framestep`), needing more evidence where the step test raised nothing near, reported at once.
"""

from __future__ import annotations

from collections import deque
from dataclasses import replace

import numpy as np

from flockcal.solver.slippage.attribution import Attribution
from flockcal.solver.slippage.framestep import FrameStep, frame_steps, noise_law, step_contrast
from flockcal.solver.slippage.stats import present


class FrameScan:
    """`SlipMonitor`'s frame-rate step test (settings `frame_step`, `frame_step_s`, `frame_step_alone`), on
    the monitor's buffer and joints: `_frame_scan` looks every other step, `_needed` says how much evidence
    an onset needs, `_neighbour_step` gives a one-joint sensor's step to its neighbour where that stepped."""

    def _init_frame_scan(self) -> None:
        s, rate_hz = self.settings, self.rate_hz
        self._half = max(4, int(round(s.frame_step_s * rate_hz)))
        self._contrast = step_contrast(self._half)
        # A step the scan finds this close to the newest onset it can test waits for the onsets just after it:
        # a neighbour's best may lie there.
        self._scan_hold = max(1, int(round(s.merge_s * rate_hz)))
        # The scan looks every other step (0.2 s of onsets at once): its cost is mostly per look, and a slip
        # it finds is then reported 0.3-0.5 s after its onset rather than 0.3-0.4 s.
        self._scan_every = 2 * max(1, int(round(s.step_s * rate_hz)))
        self._scanned = -1  # global frame index: the frame scan has tested every onset before it
        # The step test's hits, (global start frame, joint), while the frame scan may still test onsets near them.
        self._hits: deque = deque()
        # An onset is near a hit whose start is up to 0.3 s before it or 0.1 s after: the frames the frame test
        # looked at around a suspicion before the scan (a slip's own joints often cross the threshold 0.1-0.3 s
        # after its neighbours' soft tissue has).
        self._near = (int(round(0.3 * rate_hz)), int(round(0.1 * rate_hz)))
        self.frame_steps = 0  # slips confirmed by the frame-rate step test where the default did not
        # The frame scan's best step of each sensor per look: (onset time, sensor, score, evidence,
        # disagreement, jump m).
        self.frame_log: deque = deque(maxlen=2000)
        self._law: tuple | None = None  # (frame index, joints, (a, b)): the frame test's noise law, see _noise_law

    def _frame_scan(self, now: float, last: int, ready, c, l) -> list:
        """The frame-rate step test, every other step, at every onset it can now see (up to `frame_step_s`
        before global frame `last`) and every sensor with a ready joint: a slip it finds there is reported at
        once, whatever the other tests made of it. Its windows never reach back past a joint's latest event."""
        buf = self._buf
        h = self._half
        hi_g = last - h + 2
        # Onsets older than a look or so are not gone back to (the joints were not ready then, or the frames
        # went by while nothing was watched).
        lo_g = max(self._scanned, buf.first_index + h, hi_g - self._scan_every - self._chunk - self._scan_hold)
        out: list = []
        if not ready.any():
            self._scanned = max(self._scanned, hi_g)
            return out
        if hi_g - lo_g < self._scan_every:
            return out
        rows = slice(buf.slot(lo_g - h), buf.slot(last) + 1)
        base = buf.index_of(rows.start)
        pv = buf.pv[rows] & (buf.times[rows][:, None] >= self.segment_start[None, :])  # as the other tests mask
        law = self._noise_law(c, l)
        sensors = present(self.joints[ready])
        while self._hits and self._hits[0][0] < lo_g - self._near[0]:
            self._hits.popleft()  # (hits come in order of the steps that found them, near enough in start)
        while True:
            found = frame_steps(buf.g[rows], buf.Q[rows], pv, c, l, self.joints, sensors, ready, lo_g - base,
                                hi_g - base, h, self.settings.scale_floor_m, self._contrast, buf.t[rows], law)
            if not out:
                for f in found:
                    self.frame_log.append((float(buf.times[rows.start + f.onset]), self.names[f.sensor], f.score,
                                           f.evidence, f.disagreement, float(np.linalg.norm(f.step))))
            # A sensor seen through one joint cannot tell its own step from its neighbour's across that joint when
            # the joint hardly turns (and a fast-turning joint's skin blurs the difference): where the neighbour's
            # other joints show a step of their own at the same onset, it is the neighbour's. Two such tests
            # passing the frame test at one onset are evidence enough where no step-test hit is near.
            neighbour: dict[int, FrameStep | None] = {}
            good = []
            for f in found:
                if np.linalg.norm(f.step) < self.settings.min_jump_m or f.score < self.settings.frame_step_nats:
                    continue
                if len(f.joints) == 1:
                    neighbour[id(f)] = self._neighbour_step(f, rows, pv, c, l, ready, law)
                if f.score >= self._needed(f.sensor, base + f.onset) or neighbour.get(id(f)) is not None:
                    good.append(f)
            if not good:
                break
            best = max(good, key=lambda f: f.score)
            if base + best.onset >= hi_g - self._scan_hold and not out:
                # A neighbour's step at the frames just after may explain it better: decide next look.
                self._scanned = max(lo_g, base + best.onset - self._scan_hold)
                return out
            J = self.joints
            cands = [(best.sensor, 1.0)] + [(f.sensor, 0.0) for f in good if f is not best]
            other = neighbour.get(id(best))
            if other is not None:
                cands = [(other.sensor, 1.0), (best.sensor, 0.0)] + cands[1:]
                best = replace(best, sensor=other.sensor, step=other.step, score=other.score)
            mine = np.flatnonzero((J[:, 0] == best.sensor) | (J[:, 1] == best.sensor))
            self.frame_steps += 1
            att = Attribution("slip", best.sensor, -1, cands, 1.0, mine.tolist(), float(np.linalg.norm(best.step)),
                              best.score, best.step)
            onset = base + best.onset
            out.append(self._report(att, onset, float(buf.times[buf.slot(onset)]), now))
            ready = ready & self.ready
            sensors = present(self.joints[ready])
            if not len(sensors):
                break
        self._scanned = hi_g
        return out

    def _needed(self, sensor: int, onset: int) -> float:
        """The evidence a frame step needs: `frame_step` where the step test has fired on one of the sensor's
        joints with a start near its onset (the step test's suspicion, as before the scan), else
        `frame_step_alone`: every sensor at every onset is many more tries, and the hour soaks' highest scores
        where nothing slipped came from those."""
        if self.settings.frame_step_alone_nats <= self.settings.frame_step_nats:
            return self.settings.frame_step_nats
        back, ahead = self._near
        J = self.joints
        for start, q in self._hits:
            if onset - back <= start <= onset + ahead and (J[q, 0] == sensor or J[q, 1] == sensor):
                return self.settings.frame_step_nats
        return self.settings.frame_step_alone_nats

    def _neighbour_step(self, leaf, rows: slice, pv, c, l, ready, law):
        """The frame step of the sensor across a one-joint sensor's joint, on its other ready joints alone,
        within `merge_s` of the leaf's onset: returned when it passes the frame test itself, else None."""
        j = int(leaf.joints[0])
        nb = self._across(j, leaf.sensor)
        own = ready & ((self.joints[:, 0] == nb) | (self.joints[:, 1] == nb))
        own[j] = False
        if not own.any():
            return None
        buf = self._buf
        h = self._scan_hold
        found = frame_steps(buf.g[rows], buf.Q[rows], pv, c, l, self.joints, [nb], own, leaf.onset - h,
                            leaf.onset + h + 1, self._half, self.settings.scale_floor_m, self._contrast, buf.t[rows], law)
        s = self.settings
        if found and found[0].score >= s.frame_step_nats and np.linalg.norm(found[0].step) >= s.min_jump_m:
            return found[0]
        return None

    def _noise_law(self, c, l) -> tuple[np.ndarray, np.ndarray]:
        """Each joint's noise against its speed over the stored frames (`framestep.noise_law`, ten seconds or
        so: enough fast and slow frames to tell the two apart), worked out again once a second of new frames
        has come or the joints changed: a tracker's noise law changes slowly."""
        buf = self._buf
        end = buf.index_of(buf.hi)
        if self._law is None or self._law[1] is not self.joints or end - self._law[0] >= self.rate_hz:
            sl = slice(buf.lo, buf.hi)
            self._law = (end, self.joints, noise_law(buf.g[sl], buf.Q[sl], buf.t[sl], buf.pv[sl], c, l, self.joints))
        return self._law[2]
