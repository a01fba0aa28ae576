"""The slippage monitor's confirming test: a suspicion put to `attribute` on the window around its onset,
then checked against the same pose seen before (`revisit`) and between a leaf and its neighbour.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from flockcal.solver.slippage.attribution import CANDIDATE_SHARE, Attribution, Window, attribute
from flockcal.solver.slippage.pending import Suspicion
from flockcal.solver.slippage.revisit import CAME_BACK_NATS, came_back
from flockcal.solver.slippage.stats import joint_geometry, present, residual, touching


class ConfirmingTest:
    """`SlipMonitor`'s confirming test, on the monitor's buffer, pose history, pending suspicions and
    settings: `_suspicions` tests every due suspicion (`_suspicion`), `_attribute` names the sensor and
    `_leaf_or_body` settles a leaf against its neighbour. It counts what it decided, for benchmarks."""

    def _init_confirming_test(self) -> None:
        self.came_back = 0  # suspected slips that the same pose before showed to be soft tissue
        self.renamed = 0  # slips named on a leaf's neighbour that the same pose before gave to the leaf
        self.reseated = 0  # suspicions moved to a slip's later start before being confirmed
        self.confirmations = 0  # suspicions put to the confirming test (for benchmarks)

    def _suspicions(self, now: float, last: int, ready, c, l) -> tuple[bool, list]:
        """Put every pending suspicion that is due to the confirming test, oldest onset first, on the
        frames up to global index `last`. Returns (whether the quiet times or joint states changed, the events)."""
        changed, out = False, []
        for item in list(self._pending.items):
            if item in self._pending.items:  # (an event before it may have taken all its joints)
                moved, ev = self._suspicion(item, now, last, ready & self.ready, c, l)
                changed, out = changed or moved, out + ev
        return changed, out

    def _suspicion(self, item: Suspicion, now: float, last: int, ready, c, l) -> tuple[bool, list]:
        buf = self._buf
        onset, fired = item.onset, item.fired
        t_onset = float(buf.times[buf.slot(onset)])
        age = now - t_onset
        if age < self.settings.attribute_s or now < item.next_try:
            return False, []  # gather a little more evidence before naming the sensor
        self.confirmations += 1
        more_looks = age + self.settings.step_s <= self.settings.confirm_s + 1e-9
        look = self.settings.second_look_shares is not None
        # With the second look, what the first round's test decides stays as it was, except that a suspicion
        # re-seated from a refuted onset (below) must show the same verdict as the second look's slips.
        att, later = self._attribute(onset, fired, ready, c, l, last, more_looks,
                                     reseat=False if look else None, verify=item.verify)
        if att.kind is None and later is None and look:
            # The second look: scored counting `second_look` of the lagged baseline's extrapolation as noise
            # (none, as the limbs move into a new pose, where it is most of it); a slip it names stands only
            # where the same pose before the onset shows the step stayed (`_attribute`).
            second, later = self._attribute(onset, fired, ready, c, l, last, more_looks,
                                            share=self.settings.second_look_shares, verify=True)
            if later is not None:
                item.verify = True
            if second.kind == "slip" and later is None:
                att = second
            else:
                att = Attribution(None, evidence=max(att.evidence, second.evidence))
        if later is not None:
            # The step this suspicion would confirm starts well after its onset: a slip landed inside the
            # window of a suspicion kept for another look. Test it again at the step's own start.
            item.onset = later
            item.next_try = now + self.settings.step_s - 0.5 / self.rate_hz
            self._pending.items.sort(key=lambda x: x.onset)
            self.reseated += 1
            return False, []
        if att.kind is None:
            if more_looks and att.evidence > 0:
                # A step is likelier than not, but not yet by the margin: look again one step later.
                item.next_try = now + self.settings.step_s - 0.5 / self.rate_hz
                return False, []
            self._pending.judged(item, last, self._quiet)
            return True, []
        self._pending.judged(item, last, self._quiet)
        return True, [self._report(att, onset, t_onset, now)]

    def _attribute(self, onset: int, fired: np.ndarray, ready: np.ndarray, c, l, last: int, more_looks: bool = False,
                   share: tuple | None = None, reseat: bool | None = None, verify: bool = False):
        """Put the suspicion to the confirming test on the window from `baseline_s` before the onset
        to global frame `last`. Returns the attribution and, when the slip it names starts well after
        the onset, that start (global frame; else None). `share` (step test, sensor of two or more joints,
        leaf): the extrapolation counted instead of `extrapolation_share`'s; `reseat`: instead of
        `reseat_refuted`; `verify`: a slip stands only where the same pose before shows the step stayed."""
        buf = self._buf
        full = slice(buf.slot(onset - self._baseline_frames), buf.slot(last) + 1)
        onset_row = buf.slot(onset) - full.start
        # The frames long before the onset only pin the smooth part of the fit: every stride-th of them,
        # each standing for stride frames, does that at a fraction of the cost.
        cut = max(onset_row - self.window, 0)
        stride = max(1, cut // self._fit_rows)
        rows = np.concatenate([np.arange(cut % stride, cut, stride), np.arange(cut, full.stop - full.start)]) + full.start
        times = buf.times[rows]
        use = buf.pv[rows] & (times[:, None] >= self.segment_start[None, :])
        step_share, joined_share, leaf_share = self.settings.shares if share is None else share
        reseat = self.settings.reseat_refuted if reseat is None else reseat
        if share is None:
            weight = np.where(use, buf.w[rows], 0.0)
            w_joined = np.where(use, buf.wc[rows], 0.0) if joined_share != step_share else weight
            if leaf_share != step_share:  # (a share other than the step test's for a leaf: its own weights)
                var = 1.0 / np.where(weight > 0, weight, 1.0)
                extra = np.nan_to_num(self.base.sigma, nan=0.0) ** 2 * self.base.leverage(buf.Q[rows])
                weight = np.where(weight > 0, 1.0 / np.maximum(var + (leaf_share - step_share) * extra, 1e-300), 0.0)
        else:
            extra = np.nan_to_num(self.base.sigma, nan=0.0) ** 2 * self.base.leverage(buf.Q[rows])
            nv = np.where(use, buf.nv[rows], 0.0)
            live = use & (nv > 0)
            nv = np.where(live, nv, 1.0)
            weight = np.where(live, 1.0 / (nv + leaf_share * extra), 0.0)
            w_joined = np.where(live, 1.0 / (nv + joined_share * extra), 0.0) if joined_share != leaf_share else weight
        head = int(np.searchsorted(rows, full.start + cut))
        weight[:head] *= stride
        if w_joined is not weight:
            w_joined[:head] *= stride
        onset_row = int(np.searchsorted(rows, full.start + onset_row))
        post = slice(rows[onset_row], full.stop)
        g, Q = buf.g[rows], buf.Q[rows]
        near = touching(self.joints, self.joints[fired]) & ready
        u_post = residual(buf.g[post][:, near], buf.Q[post][:, near], c[near], l[near])
        weight[onset_row:, near] = _with_own_noise(u_post, weight[onset_row:, near])
        if w_joined is not weight:
            w_joined[onset_row:, near] = _with_own_noise(u_post, w_joined[onset_row:, near])

        def swapped(perm, touched):
            return joint_geometry(buf.R[post][:, perm], buf.t[post][:, perm], self.joints[touched])

        k = max(2, self.noise_frames // 4)  # a few frames each side of the onset, against the noise
        before = slice(max(full.start, post.start - k), post.start)
        after = slice(post.start, min(post.stop, post.start + k))
        pos = {}
        for name, span in (("before", before), ("after", after)):
            v = buf.valid[span]
            pos[name] = np.einsum("lm,lma->ma", v, buf.t[span]) / np.maximum(v.sum(axis=0), 1)[:, None]
            pos[name + "_ok"] = v.any(axis=0)

        def swap_plausible(a, b):
            # Two sensors that swapped streams jump into each other's place; a slip or soft tissue
            # moves a sensor by centimetres along a continuous path.
            if not (pos["before_ok"][[a, b]].all() and pos["after_ok"][[a, b]].all()):
                return False
            p0, p1 = pos["before"], pos["after"]
            stay = np.linalg.norm(p1[a] - p0[a]) + np.linalg.norm(p1[b] - p0[b])
            cross = np.linalg.norm(p1[a] - p0[b]) + np.linalg.norm(p1[b] - p0[a])
            return bool(cross < stay)

        win = Window(times, g, Q, use, weight, onset_row, c, l, swapped, swap_plausible,
                     None if w_joined is weight else w_joined)
        att = attribute(win, self.joints, self._nbrs, ready, fired, self.m, self.settings.min_jump_m,
                        self.settings.min_evidence, late_rows=self._pending.merge, min_tail=self.settings.min_frames,
                        more_looks=more_looks, reseat_refuted=reseat)
        if att.kind in ("slip", None) and att.later_row is not None:
            return att, buf.index_of(int(rows[att.later_row]))
        if att.kind == "slip":
            J = self.joints
            child, parent = J[:, 0] == att.sensor, J[:, 1] == att.sensor
            # The sensor's own skin moves with the angles of its own joints: that is the pose to match.
            pose = child | parent
            if verify:
                # Each of its joints' residuals also carries the skin of the sensor at the joint's other end,
                # which moves with that sensor's joints: all of them must be back in the same pose.
                ends = present(J[pose])
                pose = touching(J, ends)
            back = came_back(self._history, float(buf.times[post.start]), self.segment_start, buf.times[post],
                             buf.g[post], buf.Q[post], buf.pv[post], weight[onset_row:], child, parent, pose, c, l,
                             att.step)
            if back is not None and back > CAME_BACK_NATS:  # (None: poses not seen before, no verdict; the slip stands)
                self.came_back += 1
                return Attribution(None, evidence=att.evidence), None
            if verify and (back is None or back > -CAME_BACK_NATS):
                # The second look counts none of the extrapolation: skin in a new pose can pass it too. Its slip
                # stands only where the same pose before the onset shows the step stayed, by the same odds.
                return Attribution(None, evidence=att.evidence), None
            att = self._leaf_or_body(att, float(buf.times[post.start]), buf.times[post], buf.g[post], buf.Q[post],
                                     buf.pv[post], weight[onset_row:], c, l)
        return att, None

    def _leaf_or_body(self, att: Attribution, before: float, times, g, Q, pv, weight, c, l) -> Attribution:
        """A leaf's slip (a hand) and its neighbour's (the forearm) step the joint they share alike; only the
        neighbour's other joints (the elbow) tell them apart, and soft tissue in a new pose can mimic the
        neighbour's step there. A slip named on the neighbour is the leaf's where those joints sit, since
        the onset, where they sat in the same pose before it."""
        J = self.joints
        s = att.sensor
        count = np.bincount(J.ravel(), minlength=self.m)
        if count[s] < 2:
            # The other way round (a leaf's slip that is its neighbour's) is not decided here: a step at the
            # elbow is also what skin moving with a joint the pose match leaves out (the shoulder) makes (the
            # sweep renamed ten hands and feet wrongly that way, against two forearms rightly).
            return att
        mine = (J == s).any(axis=1)
        half = 0.5 * att.steps[s]
        for j in np.flatnonzero(mine):
            leaf = self._across(j, s)
            if count[leaf] != 1 or np.linalg.norm(att.steps[leaf]) < self.settings.min_jump_m:
                continue
            rest = mine.copy()
            rest[j] = False
            # The same pose: first every joint of the sensor (its skin moves with them all), then, where a
            # fast limb has not been there before, the joints that tell the two apart alone. Back means
            # nearer where they sat than half the step either way: a shift half a step along it or against
            # it is neither (the knee after a shin's slip, sweep seeds 5 and 6).
            for pose in (mine, rest):
                backs = came_back(self._history, before, self.segment_start, times, g, Q, pv, weight,
                                  rest & (J[:, 0] == s), rest & (J[:, 1] == s), pose, c, l, np.stack([half, -half]))
                if backs is not None:
                    break
            if backs is None or backs.min() <= CAME_BACK_NATS:
                continue
            back = float(backs.min())
            share = float(1.0 / (1.0 + np.exp(-back)))
            cands = [(leaf, share)] + ([(s, 1.0 - share)] if 1.0 - share >= CANDIDATE_SHARE else [])
            step = att.steps[leaf]
            self.renamed += 1
            return replace(att, sensor=leaf, candidates=cands, confidence=share, joints=[int(j)],
                           jump_m=float(np.linalg.norm(step)), step=step)
        return att


def _with_own_noise(x: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Weights 1/σ² no larger than the window's own noise allows: σ² per joint from the differences
    inside the window, where that exceeds the trailing estimate (a limb speeding up)."""
    live = weight > 0
    both = live[1:] & live[:-1]
    d2 = np.where(both, ((x[1:] - x[:-1]) ** 2).sum(axis=-1), 0.0)
    n = both.sum(axis=0)
    own = np.where(n >= 2, d2.sum(axis=0) / (6.0 * np.maximum(n, 1)), 0.0)
    with np.errstate(divide="ignore"):
        return np.where(live, 1.0 / np.maximum(1.0 / np.where(live, weight, 1.0), own[None, :]), 0.0)
