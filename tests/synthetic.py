"""Exact articulated test data: random tree skeletons with ball, hinge and rigid joints in random smooth motion.

Each body carries one sensor whose frame is the body frame; joint i (between body i and its parent) sits at
c[i] in body i's frame and l[i] in the parent's. Poses are built down the tree, so every joint holds exactly
(to rounding) unless noise is asked for. Deterministic from the seed; other areas' tests may reuse it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation


@dataclass
class Articulated:
    rotations: np.ndarray  # (n, m, 3, 3) sensor → world
    positions: np.ndarray  # (n, m, 3) metres (NaN where not valid)
    valid: np.ndarray  # (n, m) bool
    parent: np.ndarray  # (m,) int, −1 at the root (body 0)
    c: np.ndarray  # (m, 3) joint i in body i's frame (NaN at the root)
    l: np.ndarray  # (m, 3) joint i in the parent's frame
    joint_type: tuple  # (m,) "root" | "ball" | "hinge" | "rigid"
    axis_child: np.ndarray  # (m, 3) hinge axis in body i's frame (NaN unless hinge)
    axis_parent: np.ndarray  # (m, 3) the same axis in the parent's frame
    names: tuple
    rate_hz: float = 100.0

    @property
    def n_sensors(self) -> int:
        return self.rotations.shape[1]

    @property
    def joints(self) -> np.ndarray:
        """(m−1, 2) pairs (child, parent)."""
        child = np.flatnonzero(self.parent >= 0)
        return np.stack([child, self.parent[child]], axis=1)

    def bones(self) -> list[tuple[int, int, int, float]]:
        """(body, from_joint child or −1 at the root, to_joint child, length) per design.md §5."""
        out = []
        for body in range(self.n_sensors):
            kids = [int(k) for k in np.flatnonzero(self.parent == body)]
            if self.parent[body] >= 0:
                out += [(body, body, k, float(np.linalg.norm(self.c[body] - self.l[k]))) for k in kids]
            else:
                out += [(body, a, b, float(np.linalg.norm(self.l[a] - self.l[b])))
                        for x, a in enumerate(kids) for b in kids[x + 1:]]
        return out


def random_parent(m: int, rng: np.random.Generator) -> np.ndarray:
    """A random tree on m bodies rooted at 0, every parent numbered before its child."""
    parent = np.full(m, -1)
    for i in range(1, m):
        parent[i] = rng.integers(0, i)
    return parent


def _smooth(rng, n, rate, dims, amplitude):
    """(n, dims) sums of three sinusoids per dimension, amplitude ~`amplitude` (scalar or (dims,))."""
    t = np.arange(n) / rate
    f = rng.uniform(0.2, 1.5, size=(3, dims))
    ph = rng.uniform(0, 2 * np.pi, size=(3, dims))
    a = rng.uniform(0.5, 1.0, size=(3, dims)) / 2.0
    return (a[None] * np.sin(2 * np.pi * f[None] * t[:, None, None] + ph[None])).sum(axis=1) * amplitude


def articulated(
    m: int = 5,
    n: int = 400,
    seed: int = 0,
    joint_types=None,
    parent=None,
    amplitude=1.0,
    offset_scale: float = 0.15,
    dropout: float = 0.0,
    position_noise: float = 0.0,
    rotation_noise: float = 0.0,
    rate_hz: float = 100.0,
    l_override: dict | None = None,
) -> Articulated:
    """Random exact articulated motion.

    joint_types: None (all ball), one type for all, or a list over bodies (entry 0 ignored) of
    "ball" | "hinge" | "rigid" | "lowrange" (a ball joint turned widely about one axis and only by
    `amplitude`·0.1 about the others — a lumbar joint or a toe). amplitude: radians, scalar or per body.
    dropout: fraction of sensor-frames marked invalid (their positions and rotations set to NaN).
    Noise (metres, radians per axis) is added after the joints are built, as a tracker would.
    l_override {i: l} places joint i at a chosen point of its parent (e.g. two joints at one point).
    """
    rng = np.random.default_rng(seed)
    parent = random_parent(m, rng) if parent is None else np.asarray(parent, dtype=int)
    if joint_types is None or isinstance(joint_types, str):
        types = ["root"] + [joint_types or "ball"] * (m - 1)
    else:
        types = ["root"] + list(joint_types)[1:]
    amp = np.broadcast_to(np.asarray(amplitude, dtype=float), (m,))
    c = rng.normal(0, offset_scale, size=(m, 3))
    l = rng.normal(0, offset_scale, size=(m, 3))
    c[0] = l[0] = np.nan
    for i, v in (l_override or {}).items():
        l[i] = v
    axis_c = np.full((m, 3), np.nan)
    axis_p = np.full((m, 3), np.nan)
    R = np.empty((n, m, 3, 3))
    t = np.empty((n, m, 3))
    R[:, 0] = (Rotation.from_rotvec(_smooth(rng, n, rate_hz, 3, 1.2)) * Rotation.random(random_state=rng)).as_matrix()
    t[:, 0] = _smooth(rng, n, rate_hz, 3, 0.5) + np.array([2.0, -1.5, 1.0])  # far from the world origin
    for i in range(1, m):
        q0 = Rotation.random(random_state=rng)
        kind = types[i]
        if kind == "hinge":
            a = rng.normal(size=3)
            a /= np.linalg.norm(a)
            theta = _smooth(rng, n, rate_hz, 1, amp[i])
            rel = Rotation.from_rotvec(theta * a) * q0
            axis_p[i], axis_c[i] = a, q0.inv().apply(a)
        elif kind == "rigid":
            rel = Rotation.from_matrix(np.broadcast_to(q0.as_matrix(), (n, 3, 3)))
        elif kind == "lowrange":
            frame = Rotation.random(random_state=rng).as_matrix()
            scale = np.array([1.0, 0.1, 0.1]) * amp[i]
            rv = _smooth(rng, n, rate_hz, 3, scale) @ frame.T
            rel = Rotation.from_rotvec(rv) * q0
        elif kind == "ball":
            rel = Rotation.from_rotvec(_smooth(rng, n, rate_hz, 3, amp[i])) * q0
        else:
            raise ValueError(f"unknown joint type {kind!r}")
        p = parent[i]
        R[:, i] = R[:, p] @ rel.as_matrix()
        t[:, i] = np.einsum("kab,b->ka", R[:, p], l[i]) + t[:, p] - np.einsum("kab,b->ka", R[:, i], c[i])
    if rotation_noise:
        jitter = Rotation.from_rotvec(rng.normal(0, rotation_noise, size=(n * m, 3))).as_matrix()
        R = R @ jitter.reshape(n, m, 3, 3)
    if position_noise:
        t = t + rng.normal(0, position_noise, size=t.shape)
    valid = rng.random((n, m)) >= dropout
    if dropout:
        R = np.where(valid[..., None, None], R, np.nan)
        t = np.where(valid[..., None], t, np.nan)
    names = tuple(f"b{i}" for i in range(m))
    return Articulated(R, t, valid, parent, c, l, tuple(types), axis_c, axis_p, names, rate_hz)
