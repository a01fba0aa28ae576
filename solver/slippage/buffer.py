"""The slip monitor's recent frames: times, rotations, positions and validity with their global frame
index, each watched joint's geometry worked out once per frame, and the step test's deviations and
noise weights, kept until the baseline changes (solver/slippage/monitor.py).
"""

from __future__ import annotations

import numpy as np

from flockcal.solver.slippage.stats import joint_geometry


class FrameBuffer:
    """The most recent frames (times, rotations, positions, valid) with their global frame index; each
    joint's geometry (g, Q) and pair validity, worked out once when a frame arrives; and the step
    test's deviations from the baseline and noise weights, kept until the baseline changes."""

    def __init__(self, capacity: int, m: int, joints: np.ndarray):
        self.capacity = capacity
        self.joints = joints
        p = len(joints)
        size = 2 * capacity
        self.times = np.zeros(size)
        self.R = np.zeros((size, m, 3, 3))
        self.t = np.zeros((size, m, 3))
        self.valid = np.zeros((size, m), dtype=bool)
        self.g = np.zeros((size, p, 3))
        self.Q = np.zeros((size, p, 3, 3))
        self.pv = np.zeros((size, p), dtype=bool)
        self.dx = np.zeros((size, p, 3))  # deviation from the baseline, child frame
        self.dy = np.zeros((size, p, 3))  # the same in the parent frame
        self.w = np.zeros((size, p))  # the step test's 1/σ²: local noise + the baseline's extrapolation (0: unused)
        self.wc = np.zeros((size, p))  # the confirming test's 1/σ²: its own fit extrapolates no baseline
        self.nv = np.zeros((size, p))  # the frame's noise variance per axis alone (no extrapolation), m²
        self._arrays = (self.times, self.R, self.t, self.valid, self.g, self.Q, self.pv, self.dx, self.dy, self.w,
                        self.wc, self.nv)
        self.lo = self.hi = 0
        self.first_index = 0  # global index of slot lo

    def append(self, times, R, t, valid) -> int:
        """Store a batch (at most `capacity` frames); returns the global index of its first frame."""
        n = len(times)
        if self.hi + n > len(self.times):
            keep = min(self.hi - self.lo, self.capacity - n)
            src = slice(self.hi - keep, self.hi)
            for a in self._arrays:
                a[:keep] = a[src]
            self.first_index += self.hi - keep - self.lo
            self.lo, self.hi = 0, keep
        sl = slice(self.hi, self.hi + n)
        self.times[sl], self.R[sl], self.t[sl], self.valid[sl] = times, R, t, valid
        J = self.joints
        self.g[sl], self.Q[sl] = joint_geometry(R, t, J)
        self.pv[sl] = valid[:, J[:, 0]] & valid[:, J[:, 1]]
        self.dx[sl], self.dy[sl], self.w[sl], self.wc[sl], self.nv[sl] = 0.0, 0.0, 0.0, 0.0, 0.0
        self.hi += n
        if self.hi - self.lo > self.capacity:
            drop = self.hi - self.lo - self.capacity
            self.lo += drop
            self.first_index += drop
        return self.first_index + (self.hi - self.lo) - n

    def slot(self, index: int) -> int:
        """Slot of global frame `index` (clipped to what is stored)."""
        return self.lo + min(max(index - self.first_index, 0), self.hi - self.lo)

    def since(self, index: int) -> slice:
        """Slots holding global frames index… (clipped to what is still stored)."""
        return slice(self.slot(index), self.hi)

    def between(self, t0: float, t1: float) -> slice:
        times = self.times[self.lo:self.hi]
        a, b = np.searchsorted(times, [t0, t1], side="left")
        return slice(self.lo + a, self.lo + b)

    def index_of(self, slot: int) -> int:
        return self.first_index + slot - self.lo

    def rejoint(self, joints: np.ndarray) -> "FrameBuffer":
        """The same frames, indices and capacity with the geometry of another joint list worked out from
        the stored rotations and positions (the step test's deviations start afresh)."""
        J = np.asarray(joints, dtype=int).reshape(-1, 2)
        out = FrameBuffer(self.capacity, self.R.shape[1], J)
        n = self.hi - self.lo
        sl = slice(self.lo, self.hi)
        out.times[:n], out.R[:n], out.t[:n], out.valid[:n] = self.times[sl], self.R[sl], self.t[sl], self.valid[sl]
        out.g[:n], out.Q[:n] = joint_geometry(self.R[sl], self.t[sl], J)
        out.pv[:n] = self.valid[sl][:, J[:, 0]] & self.valid[sl][:, J[:, 1]]
        out.lo, out.hi, out.first_index = 0, n, self.first_index
        return out
