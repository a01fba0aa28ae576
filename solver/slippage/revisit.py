"""Soft tissue comes back when the pose comes back: the slip monitor's last check of a suspected slip
compares each joint's residual now with its residual when the body was last in the same pose.

A slip leaves the residual a step away from what it was in that pose; soft tissue, however fast it
swings, puts it back where it was. Poses the take has not been in yet give no verdict.
"""

from __future__ import annotations

import numpy as np

from flockcal.solver.slippage.stats import joint_geometry, residual

# Two poses are the same when every joint involved is within this angle of where it was (radians): soft
# tissue moves a sensor by about a centimetre per radian, so 4° leaves well under a millimetre.
SAME_POSE_RAD = np.radians(4.0)
# A slip is dropped when its frames favour "back where it was" over "a step away" by this many nats
# (20 : 1), from at least this many frames of the same pose.
CAME_BACK_NATS = 3.0
MIN_MATCHES = 5


class PoseHistory:
    """The last `seconds` of every sensor's pose and validity, and every watched joint's geometry (g, Q)
    and pair validity, at about `rate_hz` / `every` (a pose needs no more), so a pose can be looked up
    after the frame buffer has let it go. The sensors' poses let another joint list take the history
    over (`rejoint`): a joint new to the tree has its past poses at once."""

    def __init__(self, joints: np.ndarray, m: int, rate_hz: float, seconds: float, every: int):
        self.every = max(1, int(every))
        cap = int(np.ceil(seconds * rate_hz / self.every)) + 1
        self.times = np.full(cap, np.nan)
        self.R = np.zeros((cap, m, 3, 3))
        self.t = np.zeros((cap, m, 3))
        self.valid = np.zeros((cap, m), dtype=bool)
        self.next = 0  # ring position
        self.count = 0
        self._geometry(joints)

    def _geometry(self, joints: np.ndarray) -> None:
        J = np.asarray(joints, dtype=int).reshape(-1, 2)
        self.joints = J
        self.g, self.Q = joint_geometry(self.R, self.t, J)
        self.pv = self.valid[:, J[:, 0]] & self.valid[:, J[:, 1]]

    def rejoint(self, joints: np.ndarray) -> None:
        """The joints' geometry for another joint list, from the poses kept."""
        self._geometry(joints)

    def append(self, first_index: int, times, R, t, valid, g, Q, pv) -> None:
        """Frames of global indices first_index… (poses R, t, valid and the joints' g, Q, pv worked out
        already); every `every`-th global frame is kept."""
        keep = np.flatnonzero((first_index + np.arange(len(times))) % self.every == 0)
        if not len(keep):
            return
        cap = len(self.times)
        at = (self.next + np.arange(len(keep))) % cap
        self.times[at], self.R[at], self.t[at], self.valid[at] = times[keep], R[keep], t[keep], valid[keep]
        self.g[at], self.Q[at], self.pv[at] = g[keep], Q[keep], pv[keep]
        self.next = int((self.next + len(keep)) % cap)
        self.count = min(self.count + len(keep), cap)


def came_back(history: PoseHistory, before: float, since: np.ndarray, times, g, Q, pv, weight,
              child: np.ndarray, parent: np.ndarray, pose: np.ndarray, c, l,
              step: np.ndarray) -> float | np.ndarray | None:
    """How much likelier (nats) the frames since a suspected slip of a sensor (the child of joints `child`,
    the parent of joints `parent`, boolean over all joints) sit where the same joints sat in the same pose
    before it than a `step` (3,) away in the sensor's own frame (over CAME_BACK_NATS: they came back);
    None while the frames since are all in poses not seen before. Several steps (k, 3) against one pose
    match give (k,).

    history: poses up to time `before` (the onset) are looked up, from `since` (P,) on for each joint
    (its current segment); times, g, Q, pv, weight: the frames since the onset; pose (P,) bool: the
    joints whose angles move the skin under the sensor's joints; c, l: the current estimates.
    """
    mine = child | parent
    n = history.count
    if not mine.any() or n == 0:
        return None
    h = np.arange(n)
    need = pose | mine
    usable = (history.times[h] < before) & history.pv[h][:, need].all(axis=1)
    usable &= (history.times[h][:, None] >= since[None, need]).all(axis=1)
    h = h[usable]
    live = pv[:, need].all(axis=1)
    if len(h) < MIN_MATCHES or live.sum() < MIN_MATCHES:
        return None
    # The pose distance is the worst joint's: ‖Q − Q'‖² (Frobenius) is 4 (1 − cos θ) ≈ 2 θ².
    a = Q[live][:, need].reshape(int(live.sum()), -1, 9)
    b = history.Q[h][:, need].reshape(len(h), -1, 9)
    d2 = ((a[:, None] - b[None]) ** 2).sum(axis=-1).max(axis=-1)  # (post, history)
    best = d2.argmin(axis=1)
    matched = d2[np.arange(len(best)), best] <= 4 * (1 - np.cos(SAME_POSE_RAD))
    if matched.sum() < MIN_MATCHES:
        return None  # poses not seen before: no verdict yet
    rows = np.flatnonzero(live)[matched]
    then = h[best[matched]]
    J = np.flatnonzero(mine)
    now_x = residual(g[rows][:, J], Q[rows][:, J], c[J], l[J])
    then_x = residual(history.g[then][:, J], history.Q[then][:, J], c[J], l[J])
    # In the sensor's own frame: +u where it is the child, −Qᵀu where it is the parent.
    sign_parent = parent[J]

    def own(u, Qs):
        return np.where(sign_parent[None, :, None], -(Qs.swapaxes(-1, -2) @ u[..., None])[..., 0], u)

    diff = own(now_x, Q[rows][:, J]) - own(then_x, history.Q[then][:, J])
    w = 0.5 * weight[rows][:, J]  # a difference of two frames has twice a frame's variance
    info = w.sum()
    if not info > 0:
        return None
    mean = (diff * w[..., None]).sum(axis=(0, 1)) / info
    step = np.asarray(step, dtype=float)
    favour_back = 0.5 * info * (((mean - step) ** 2).sum(axis=-1) - (mean**2).sum())
    return float(favour_back) if step.ndim == 1 else favour_back
