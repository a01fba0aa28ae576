"""A session's calibration progress, fit after fit (solver/progress.py defines it for one fit): a joint
counts once it has held for CONFIRM_S, stays counted until a slip or a real loss of fit (`progress.lost`)
undoes it, and the published figure goes down only for a reason an entry states. Each joint's history is
one `JointTrack`, each sensor's one `SensorTrack`.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, replace
from itertools import count
from typing import TYPE_CHECKING

from flockcal.solver.progress import (
    CONFIRM_S, NOT_DONE_CAP, SETTLING_SHARE, FitFacts, JointState, Profile, Progress, Standing, Steadiness, Undone,
    lost, percent, standing, summarise,
)
from flockcal.solver.progress_words import stall_prompt

if TYPE_CHECKING:
    from flockcal.solver.slippage.monitor import SlipEvent, SwapEvent

# A patient prompt once the ring has gained less than STALL_GAIN over STALL_S of session time: a guest who
# stopped moving (standing still with skin-mounted sensors, the ring still creeps up by 0.5 % a second as
# sway pins a joint or two) or one joint that will not come; a moving guest gains a joint (6.7 %) in 2-3 s.
STALL_S = 8.0
STALL_GAIN = 0.1


@dataclass(frozen=True)
class Latch:
    """A joint done: as a hinge or not, since when, between which bodies; `seq` orders latches as made."""

    joint: str
    hinge: bool
    time_s: float
    bodies: tuple
    seq: int


@dataclass
class JointTrack:
    """One joint's history in a session, keyed by its two sensors."""

    latch: Latch | None = None  # done
    meeting_since: float | None = None  # session time since which it has met the target
    undone: Undone | None = None  # done once, undone since (its time unrounded)
    best: tuple | None = None  # (share, hinge): the best share a pinning joint reached
    pinning_since: float | None = None  # session time since which it has been determined
    first_info: float | None = None  # kiosk: its information when it was first determined


@dataclass
class SensorTrack:
    """One sensor's history: its joint's held share and what it was credited against."""

    slipped: int = -1  # epoch of its latest slip
    done_parent: tuple | None = None  # (the parent it was last done against,)
    floor: float | None = None  # the share its joint last showed: the ring holds it through tree re-links (#19)
    credited: frozenset = frozenset()  # the pair that floor was reached with


class StallClock:
    """How long the published figure has gained less than STALL_GAIN (`tick`), from a pruned history."""

    def __init__(self):
        self._history: deque = deque()  # (time_s, published figure)
        # The entries of `_history` newer than every later lower-or-equal figure ((index, time_s, figure),
        # figures rising towards the newest): where the backward search can end. `_gone`: entries trimmed
        # off `_history` so far, `_n`: ever appended (indices).
        self._lows: deque = deque()
        self._n = self._gone = 0

    def tick(self, figure: float, done: bool, time_s: float) -> float | None:
        """`stalled_s` after publishing `figure` at `time_s`: the idle time once it is STALL_S or more."""
        hist, lows = self._history, self._lows
        if done:
            hist.clear()
            lows.clear()
            self._gone = self._n
        hist.append((time_s, figure))
        # An entry with a figure at or above this one can no longer be the newest low enough: drop it from
        # the search (at 30 fits a second a plateau held 80 s of history, scanned on every fit).
        while lows and lows[-1][2] >= figure:
            lows.pop()
        lows.append((self._n, time_s, figure))
        self._n += 1
        while len(hist) > 2 and hist[1][0] <= time_s - 10 * STALL_S:
            hist.popleft()
            self._gone += 1
        while lows[0][0] < self._gone:
            lows.popleft()
        # The newest entry whose figure is at least STALL_GAIN below this one, else the oldest kept.
        since = next((t for _, t, p in reversed(lows) if p <= figure - STALL_GAIN), hist[0][0])
        idle = time_s - since
        return round(idle, 1) if idle >= STALL_S and not done else None


def slip_sensors(event) -> tuple[set, float]:
    """(the sensors a slip event moved, its time): a `SlipEvent`, or a `SwapEvent` (both sensors). A stored
    §5 entry is read into one first (`calibration_json.event_from_json`)."""
    sensors = (event.a, event.b) if event.kind == "swap" else (event.sensor,)
    return {s for s in sensors if s}, float(event.time_s)


class ProgressTracker:
    """Progress of one session, fit after fit. A joint is done once it has been "done" in the sense of
    `standing` for CONFIRM_S; it then stays done until a slip of one of its sensors or a real loss of fit
    (`lost`) undoes it, and its entry says why until it is done again. `done` (the whole session) needs
    every joint done and one fit in which every joint meets the target at once.

    Joints are keyed by their two bodies, so re-rooting the tree keeps them. `slip()` takes the slip
    events; fits are stamped with the slip `epoch` their accumulator copy had, so a fit begun before a slip
    was applied cannot mark that sensor's joints done again.
    """

    def __init__(self, target_m: float, tolerance_m: float | None = None, tree_fixed: bool = False,
                 confirm_s: float = CONFIRM_S, steady: Steadiness | None = None):
        self.target_m = float(target_m)
        self.tolerance_m = self.target_m if tolerance_m is None else float(tolerance_m)
        self.tree_fixed = bool(tree_fixed)
        self.confirm_s = float(confirm_s)
        self.steady = steady
        self.profile: Profile | None = None
        self.joints: dict[frozenset, JointTrack] = {}
        self.sensors: dict[str, SensorTrack] = {}
        self.stall = StallClock()
        self._ring = 0.0  # the figure last published (`_hold_ring`)
        self._recent: deque = deque()  # (time_s, {child: parent}, {bone key: length}) over the steadiness window
        self._seq = count()
        self.done = False
        self.done_at_s: float | None = None
        self.latest: Progress | None = None

    @classmethod
    def for_profile(cls, prof: Profile, tree_fixed: bool = False) -> "ProgressTracker":
        """A session's tracker under `prof` ("stage" or "kiosk"); its documents name the profile and its rule."""
        tracker = cls(prof.target_m, prof.tolerance_m, tree_fixed, steady=prof.steady)
        tracker.profile = prof
        return tracker

    def joint(self, child: str, parent: str | None) -> JointTrack:
        """The history of the joint between `child` and `parent` (made empty on first use)."""
        return self._track(frozenset((child, parent)))

    def _track(self, pair: frozenset) -> JointTrack:
        track = self.joints.get(pair)
        if track is None:
            track = self.joints[pair] = JointTrack()
        return track

    def _sensor(self, name: str) -> SensorTrack:
        track = self.sensors.get(name)
        if track is None:
            track = self.sensors[name] = SensorTrack()
        return track

    def _latched(self) -> list[tuple[frozenset, JointTrack]]:
        """The done joints, in the order they were latched."""
        return sorted(((p, t) for p, t in self.joints.items() if t.latch is not None), key=lambda pt: pt[1].latch.seq)

    def slip(self, event: SlipEvent | SwapEvent, epoch: int) -> list[str]:
        """Undo every done joint of the slipped sensor(s) (a swap: both); returns the joints undone."""
        sensors, when = slip_sensors(event)
        for s in sensors:
            self._sensor(s).slipped = int(epoch)
        for pair, track in self.joints.items():
            if pair & sensors:
                track.meeting_since = track.best = track.pinning_since = track.first_info = None
        for child, st in self.sensors.items():
            was = st.done_parent[0] if st.done_parent is not None else None
            if child in sensors or was in sensors or st.credited & sensors:
                st.floor = None
        hit = []
        for pair, track in self.joints.items():
            if not pair & sensors:
                continue
            u = track.undone
            # The monitor confirms a slip some 0.2-1 s after its onset; a joint of that sensor whose fit was
            # lost in between lost it to the slip, and its entry should say so rather than "loss".
            was_lost = u is not None and u.reason == "loss" and u.time_s >= when
            if track.latch is not None:
                hit.append(track.latch.joint)
                track.latch = None
            elif not was_lost:
                continue
            track.undone = Undone("slip", when, sorted(pair & sensors)[0])
        return sorted(hit)

    def add_fit(self, fit, time_s: float, epoch: int = 0) -> Progress:
        """The session's progress after a new fit (a Calibration, or its §5 dict; its data up to `time_s`,
        session clock; begun at slip `epoch`)."""
        f = FitFacts.of(fit)
        time_s = float(time_s)
        items = standing(f, self.target_m, self.tolerance_m, self.tree_fixed)
        if self.steady is not None:
            self._steadiness(items, f, time_s)
        self._carry_over(items)
        all_clear = bool(items)
        for it in items:
            pair = frozenset((it.joint, it.parent))
            track = self._track(pair)
            j = f.joints.get(it.joint)
            meets = it.state is JointState.DONE
            it.meets_now = meets
            all_clear &= meets
            stale = max(self.sensors[s].slipped if s in self.sensors else -1 for s in pair) > epoch
            latch = track.latch
            if latch is not None and not meets and lost(j, latch.hinge, self.target_m):
                track.latch = latch = None
                track.undone = Undone("loss", time_s, it.joint)
                self._sensor(it.joint).floor = None
            if latch is None:
                if meets and not stale:
                    if track.meeting_since is None:
                        track.meeting_since = time_s
                    if time_s - track.meeting_since >= self.confirm_s - 1e-9:
                        latch = track.latch = Latch(it.joint, j.hinge, time_s, it.bodies, next(self._seq))
                        track.undone = None
                    else:
                        it.state, it.progress = JointState.CONFIRMING, 0.0
                else:
                    track.meeting_since = None
            it.done = latch is not None
            it.undone = None
            if not it.done:
                self._hold(it, track, j, time_s, stale)
            sensor = self._sensor(it.joint)
            if it.done:
                it.state = JointState.DONE  # done stays done through a wobble of the newest fit
                sensor.done_parent = (it.parent,)
            elif track.undone is not None:
                it.undone = replace(track.undone, time_s=round(track.undone.time_s, 3))
            elif sensor.done_parent is not None and sensor.done_parent[0] != it.parent:
                it.undone = Undone("tree", round(time_s, 3), it.joint, it.parent, sensor.done_parent[0])
        self._hold_floor(items)
        every = bool(items) and all(it.done for it in items)
        # Stage: one fit must also pin every joint at once. Kiosk: each joint counted only once it held still,
        # so every joint counted is done (and the ring never shows every joint ticked below 100 %).
        if not self.done and every and (all_clear or self.steady is not None):
            self.done, self.done_at_s = True, round(time_s, 3)
        elif self.done and not every:
            self.done, self.done_at_s = False, None
        doc = self._hold_ring(summarise(items, self.target_m, self.done, self.done_at_s), items)
        stalled = self.stall.tick(doc.progress, doc.done, time_s)
        prompt = None
        if stalled is not None and doc.missing:
            first = doc.joint(doc.missing[0])
            prompt = stall_prompt(first.joint, first.parent, first.label)
        prof = self.profile
        self.latest = replace(doc, tracked=True, stalled_s=stalled, prompt=prompt,
                              profile=None if prof is None else prof.name, rule=None if prof is None else prof.rule)
        return self.latest

    def _steadiness(self, items: list[Standing], f: FitFacts, time_s: float) -> None:
        """Kiosk: a pinned joint (DONE in `standing`) counts only once more data no longer changes it;
        until then it is SETTLING, and its entry says which test it waits for."""
        st = self.steady
        bones = f.bones
        self._recent.append((time_s, f.parent, bones))
        while len(self._recent) > 1 and self._recent[1][0] <= time_s - st.window_s:
            self._recent.popleft()
        covered = self._recent[0][0] <= time_s - st.window_s + 1e-9
        frames = float(f.frames)
        for it in items:
            pair = frozenset((it.joint, it.parent))
            j = f.joints.get(it.joint)
            if j is None or not j.determined:
                if pair in self.joints:
                    self.joints[pair].first_info = None
                continue
            info = frames * max(j.coverage[1 if j.hinge else 0], 0.0)
            # Since it was first determined (a place in the tree still unsettled does not restart it).
            track = self._track(pair)
            if track.first_info is None:
                track.first_info = info
            first = track.first_info
            if it.state is not JointState.DONE:
                continue
            child = it.joint
            mine = [k for k in bones if child in (k[1], k[2])]
            moved = 0.0
            for _, par, past in self._recent:
                if par.get(child) != it.parent or any(k not in past for k in mine):
                    moved = math.inf
                    break
                moved = max([moved, *(abs(past[k] - bones[k]) for k in mine)])
            err = max(j.needed())
            noise = max(j.needed(noise=True))
            skin = err >= st.skin_ratio * noise
            if err <= st.noise_m and not skin:
                continue  # pinned as firmly as the stage asks on white residuals: more frames would only confirm it
            if not skin:
                # White residuals (no skin to speak of): more frames do shrink the error, so wait for them.
                it.state, it.progress = JointState.PINNING, min(1.0, (st.noise_m / err) ** 2)
                continue
            if noise > st.noise_m:
                why = (f"pinned to {1000 * self.tolerance_m:.0f} mm; counted once the frames pin it to "
                       f"{1000 * st.noise_m:.1f} mm" + (f" (now {1000 * noise:.1f} mm)" if math.isfinite(noise) else ""))
            elif info < (1.0 + st.growth) * first:
                why = "pinned just now; counted once it has moved on a little more"
            elif not mine:
                why = "pinned; counted once a joint next to it is too (it ends no bone yet)"
            elif not covered or moved > st.within_m:
                why = (f"pinned; counted once its bones hold within {1000 * st.within_m:.0f} mm over "
                       f"{st.window_s:g} s" + (f" (moved {1000 * moved:.1f} mm)" if math.isfinite(moved) and covered else ""))
            else:
                continue
            it.state, it.progress, it.settling = JointState.SETTLING, SETTLING_SHARE, why

    def _hold(self, it: Standing, track: JointTrack, j, time_s: float, stale: bool) -> None:
        """A joint on its way to a stricter target than the tolerance shows the best share it has reached
        (PINNING), so the ring does not follow its error's wobbles back either; a real loss (`lost`, against
        the tolerance it was determined to) resets it. As for done, the share counts once the joint has been
        determined for CONFIRM_S."""
        if it.state in (JointState.PINNING, JointState.CONFIRMING):
            if track.pinning_since is None:
                track.pinning_since = time_s
            since = track.pinning_since
        else:
            since = track.pinning_since = None
        best = track.best
        if best is not None and lost(j, best[1], self.tolerance_m):
            track.best = best = None
            track.undone = Undone("loss", time_s, it.joint)
            self._sensor(it.joint).floor = None
        held = since is not None and time_s - since >= self.confirm_s - 1e-9
        if it.state is JointState.PINNING and held and not stale and (best is None or it.progress > best[0]):
            best = track.best = (it.progress, j.hinge)
        # Kiosk: a joint pinned to its tolerance and waiting to hold still, or to count, shows that share.
        base = (SETTLING_SHARE if self.steady is not None and it.state in (JointState.SETTLING, JointState.CONFIRMING)
                else 0.0)
        it.progress = max(best[0] if best is not None else 0.0, base)

    def _hold_floor(self, items: list[Standing]) -> None:
        """A sensor's share never falls but for a stated reason. Under soft tissue the tree re-links a
        joint between two neighbours that move almost as one (a thigh between pelvis and abdomen, back and
        forth): its best share is kept per pair, so each re-link showed the other pair's share and the ring
        went back (20 times in 8 guests) with no reason given. The share is held per sensor instead, and
        dropped only by a slip or a loss of fit (`slip`, `lost`), which the entry's `undone` names.
        A done joint the tree moves elsewhere is no longer done (its `undone` says "tree"): it shows just
        under 1 until it is done again."""
        for it in items:
            sensor = self._sensor(it.joint)
            value = 1.0 if it.done else it.progress
            held = sensor.floor
            if held is not None and value < held and not it.done:
                # A share below 1 is held as it was; a joint done once shows just under 1 (it is not done).
                it.progress = held if held < 1.0 else NOT_DONE_CAP
                value = it.progress
            if held is None or value > held:
                sensor.floor = value
                sensor.credited = frozenset((it.joint, it.parent))

    def _hold_ring(self, doc: Progress, items: list[Standing]) -> Progress:
        """The published figure goes down only for a reason an entry states (a slip, a loss, a re-link):
        in the first seconds the tree re-roots and a sensor that was the root joins the mean at 0, which
        took the ring back 5 times in 20 soft-tissue guests with nothing to say why."""
        floor = self._ring
        stated = any(it.undone is not None for it in items)
        if doc.progress < floor and not stated and not doc.done:
            doc = replace(doc, progress=floor, percent=percent(floor))
        self._ring = doc.progress
        return doc

    def _carry_over(self, items: list[Standing]) -> None:
        """Re-key done joints whose rigid group came apart: a joint done between bodies A and B (each a rigid
        group then) is the joint the tree now draws between a member of A and a member of B."""
        current = {frozenset((it.joint, it.parent)): it for it in items}
        latched = None
        for pair, it in current.items():
            track = self.joints.get(pair)
            if track is not None and track.latch is not None:
                continue
            if latched is None:
                latched = self._latched()
            x, p = it.joint, it.parent
            for k, (old, old_track) in enumerate(latched):
                a, b = old_track.latch.bodies
                if old not in current and ((x in a and p in b) or (x in b and p in a)):
                    latch, old_track.latch = old_track.latch, None
                    new = self._track(pair)
                    new.latch = replace(latch, joint=x, bodies=it.bodies, seq=next(self._seq))
                    latched[k:k + 1] = []
                    latched.append((pair, new))
                    break
