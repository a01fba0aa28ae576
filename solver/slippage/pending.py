"""The slip monitor's pending suspicions, kept apart by onset: soft tissue on some joints and a real slip
a moment later on others (or the same ones) are separate suspicions, each put to the confirming test at
its own onset, and a refuted one quiets only its own joints, never past a later suspicion's onset.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flockcal.solver.slippage.stats import present


@dataclass(eq=False)  # identity: two suspicions with the same onset are still two
class Suspicion:
    onset: int  # global frame index: the step's first frame
    fired: np.ndarray  # (p,) bool: joints whose step test fired with a start near the onset
    next_try: float = -np.inf  # no confirming test before this time (a likely step gets another look)
    verify: bool = False  # re-seated by the second look: a slip needs the same pose before to show it stayed


class PendingSuspicions:
    """Suspicions awaiting the confirming test, oldest onset first.

    A joint's hit (its step test passing the threshold, with the start the test found) joins the pending
    suspicion whose onset is within `merge` frames of that start: a slip's joints cross the threshold
    at different moments but all find the same start. A hit further from every onset is a new
    suspicion; hits close to each other form one, with their earliest start as its onset. At most
    `limit` are kept: beyond that a hit joins the nearest (a flood of starts is soft tissue, and testing
    each would cost more than it could find).
    """

    def __init__(self, p: int, merge: int, limit: int = 4):
        self.p = int(p)
        self.merge = max(0, int(merge))
        self.limit = max(1, int(limit))
        self.items: list[Suspicion] = []

    def __bool__(self) -> bool:
        return bool(self.items)

    def __len__(self) -> int:
        return len(self.items)

    def add(self, hit: np.ndarray, start: np.ndarray) -> None:
        """Take one step's hits (p,) bool with each joint's step start (p,) global frame index."""
        joints = np.flatnonzero(hit)
        if not len(joints):
            return
        s = start[joints]
        if self.items:
            onsets = np.array([x.onset for x in self.items])
            d = np.abs(s[:, None] - onsets[None, :])  # (hits, pending)
            near = d.argmin(axis=1)
            close = d[np.arange(len(joints)), near] <= self.merge
            for k in present(near[close]).tolist():
                self.items[k].fired[joints[close & (near == k)]] = True
            joints, s = joints[~close], s[~close]
        if not len(joints):
            return
        order = np.argsort(s, kind="stable")
        joints, s = joints[order], s[order]
        # Starts within `merge` of the previous one belong to the same step.
        group = np.concatenate([[0], np.cumsum(np.diff(s) > self.merge)])
        for g in range(int(group[-1]) + 1):
            mine = group == g
            if len(self.items) >= self.limit:
                onsets = np.array([x.onset for x in self.items])
                k = int(np.abs(onsets - s[mine][0]).argmin())
                self.items[k].fired[joints[mine]] = True
                continue
            fired = np.zeros(self.p, dtype=bool)
            fired[joints[mine]] = True
            self.items.append(Suspicion(int(s[mine][0]), fired))
        self.items.sort(key=lambda x: x.onset)

    def judged(self, item: Suspicion, last: int, quiet: np.ndarray) -> None:
        """Drop a suspicion the confirming test has decided on, on frames up to `last`, and move `quiet`
        (p,) (no step may start before it) for its joints: past the frames it was judged on, so the same
        evidence is not raised again, but not past the onset of a later suspicion holding the joint,
        whose own evidence starts there."""
        self.items.remove(item)
        upto = np.where(item.fired, last + 1, -1)
        for other in self.items:
            if other.onset > item.onset:
                upto = np.where(other.fired & item.fired, np.minimum(upto, other.onset), upto)
        np.maximum(quiet, upto, out=quiet)

    def forget(self, joints: np.ndarray) -> None:
        """Joints (p,) bool that start a new segment (an event): no suspicion holds them any longer."""
        for x in self.items:
            x.fired &= ~joints
        self.items = [x for x in self.items if x.fired.any()]

    def rejoint(self, keep: np.ndarray, kept: np.ndarray) -> None:
        """Another joint list: joint k of it is joint keep[k] of this one where kept[k]."""
        k = np.maximum(keep, 0)
        for x in self.items:
            x.fired = kept & x.fired[k]
        self.p = len(keep)
        self.items = [x for x in self.items if x.fired.any()]
