"""The humanoid's segments frame by frame, through a fit: where each humanoid bone's segment starts and how it
is turned, on the humanoid's world axes (solver/humanoid.py's convention) — what the live VRPN and VMC streams
send. `humanoid_rig(cal, hum)` is worked out once per fit; `HumanoidRig.segments` is one product over frames.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from flockcal.solver.humanoid import BONES, Humanoid, proximal_points, tpose_offsets
from flockcal.solver.reconstruct import Articulation, ArticulationError, articulation, reconstruct


@dataclass(frozen=True, eq=False)
class HumanoidRig:
    """A fit read as a humanoid: the articulation rooted at the hips body and, per BONES entry k (k = the
    VRPN sensor number), its body (`sensor[k]`, −1 when no body is that bone), its parent bone
    (`parent_bone[k]`, −1 at the hips or when no ancestor has a bone) and its T-pose offset from that parent
    bone's start on the humanoid's world axes (`local_offset[k]`, metres; a fitted bone's length for a limb).
    """

    names: tuple[str, ...]
    humanoid: Humanoid
    art: Articulation  # rooted at the hips body, bodies in `names` order, complete
    start: np.ndarray  # (m, 3) each body's bone start in its own sensor frame (`proximal_points`)
    sensor: np.ndarray  # (16,) int
    parent_bone: np.ndarray  # (16,) int
    local_offset: np.ndarray  # (16, 3)

    @cached_property
    def present(self) -> np.ndarray:
        """Indices k of the BONES that have a body, in BONES order."""
        return np.flatnonzero(self.sensor >= 0)

    def segments(self, rotations: np.ndarray, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """((n, K, 3) positions, (n, K, 3, 3) rotations) of the K `present` bones' segments on the humanoid's
        world axes (metres, origin the tracker's), from sensor poses (n, m, 3, 3) / (n, m, 3) in tracker
        world with every slot held valid (`reconstruct.held_poses`). Positions are each segment's start
        played through the fit (only the rotations and the hips sensor's position drive it, as
        `reconstruct` plays a take), so a bone and its parent bone are exactly the fitted bone apart; NaN
        in the subtree of a sensor with no pose yet."""
        R, t = np.asarray(rotations, dtype=float), np.asarray(positions, dtype=float)
        return self.play(self.inputs(R, t, np.empty((len(R), self.width))))

    @property
    def width(self) -> int:
        """Columns of `play`'s input: a frame's sensor rotations flattened, then the root sensor's position."""
        return 9 * self.art.n_bodies + 3

    def inputs(self, rotations: np.ndarray, positions: np.ndarray, out: np.ndarray) -> np.ndarray:
        """`out` ((n, width)) filled with `play`'s input from sensor poses (n, m, 3, 3) / (n, m, 3): a caller
        with frames in several batches writes each batch's rows in place instead of joining them first."""
        n, m = len(out), self.art.n_bodies
        out[:, :9 * m] = rotations.reshape(n, 9 * m)
        out[:, 9 * m:] = positions[:, self.art.root]
        return out

    def play(self, x: np.ndarray, finite: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """`segments` of frames given as `inputs` rows (n, width); `finite`: the caller knows every input is
        (frames with every sensor valid), so none is looked for."""
        n, K = len(x), len(self.present)
        # Both are linear in the rotations' entries and the root sensor's position: one product for the whole
        # batch (a live hand-over's frames) with the map `_walk` gives, instead of ~15 numpy calls a batch.
        if finite or np.isfinite(np.add.reduce(x, axis=None)):  # a sum is finite only when every term is
            y = x @ self._map
        else:  # a sensor with no pose yet: NaN in what depends on it (its subtree), the rest as ever
            finite = np.isfinite(x)
            y = np.where(finite, x, 0.0) @ self._map
            y[~finite @ self._reach] = np.nan
        return y[:, :3 * K].reshape(n, K, 3), y[:, 3 * K:].reshape(n, K, 3, 3)

    @cached_property
    def _map(self) -> np.ndarray:
        """(9m + 3, 12K): the K bones' positions then rotations (flattened) as linear in one frame's sensor
        rotations (flattened) and the root sensor's position. A bone's start is reconstruct's walk down the
        tree as one sum along its body's path from the root, t_root + Σ (R_p l_a − R_a c_a) over the bodies
        a on the way, plus its own R_s start; its rotation R_s frames_s; both on the humanoid's world axes."""
        m, K = self.art.n_bodies, len(self.present)
        s, path, start, up, l, c = self._plan
        world, frames = self.humanoid.world, self.humanoid.frames[s]
        # coef[k, b, j]: what entry (i, j) of body b's rotation adds to bone k's start along row i.
        parent_of = (up[:, None] == np.arange(m)).astype(float)  # (m, m): a body's parent
        coef = (path @ (parent_of[:, :, None] * l[:, None, :, 0]).reshape(m, 3 * m)).reshape(K, m, 3)
        coef -= path[:, :, None] * c[None, :, :, 0]
        coef[np.arange(K), s] += start[:, :, 0]
        out = np.zeros((9 * m + 3, 12 * K))
        body = out[:9 * m].reshape(m, 3, 3, 12 * K)  # views: rows (body, i, j), columns (bone, ...)
        body[..., :3 * K].reshape(m, 3, 3, K, 3)[...] = np.einsum("kbj,xi->bijkx", coef, world)
        out[9 * m:, :3 * K] = np.tile(world.T, K)
        # A bone's rotation turns with its own body only.
        body[..., 3 * K:].reshape(m, 3, 3, K, 3, 3)[s, :, :, np.arange(K)] = np.einsum("xi,kjy->kijxy", world, frames)
        return out

    @cached_property
    def _reach(self) -> np.ndarray:
        """(9m + 3, 12K) bool: which inputs of `_map` each output is played from, whether or not their terms
        cancel (a bone's start does not turn with its own sensor): a bone's position from the root sensor's
        position, its own sensor and every body on its path from the root and that body's parent; its
        rotation from its own sensor."""
        m, K = self.art.n_bodies, len(self.present)
        s, path, _start, up, _l, _c = self._plan
        body = path > 0
        body |= (body @ (up[:, None] == np.arange(m))) > 0  # each path body's parent
        body[np.arange(K), s] = True
        reach = np.zeros((m + 1, 12 * K), dtype=bool)
        reach[:m, :3 * K] = np.repeat(body.T, 3, axis=1)
        reach[m, :3 * K] = True  # the root sensor's position, the last row
        reach[s[:, None], 3 * K + np.arange(9 * K).reshape(K, 9)] = True
        return np.repeat(reach, [9] * m + [3], axis=0)

    @cached_property
    def _plan(self) -> tuple:
        """What `segments` reads, indexed once per rig: the present bones' bodies, their paths from the root
        ((K, m): 1 where body a lies on the way to the bone's body, the root left out) and starts; each
        body's parent (the root its own, its step unused) and joint points as columns."""
        art = self.art
        path = np.zeros((art.n_bodies, art.n_bodies))
        for j in art.order[1:]:
            path[j] = path[art.parent[j]]
            path[j, j] = 1.0
        s = self.sensor[self.present]
        up = np.where(art.parent < 0, np.arange(art.n_bodies), art.parent)
        return s, path[s], self.start[s][:, :, None], up, art.l[:, :, None], art.c[:, :, None]


def humanoid_rig(cal, hum: Humanoid, frames=None) -> HumanoidRig:
    """The rig of `cal` (a Calibration or §5 dict) read through `hum`. `frames` (rotations, positions, valid
    arrays over some frames of the take) place sensors that ride rigidly on their parent
    (`Articulation.completed`). Raises ArticulationError for a fit that cannot drive a humanoid (no hips, not
    human-shaped)."""
    if not hum.human:
        raise ArticulationError(f"the tree is not human-shaped ({hum.reason}); no humanoid to stream")
    hips = hum.sensor("hips")
    if hips is None:
        raise ArticulationError("no body is the hips; no humanoid to stream")
    art = articulation(cal)
    if art.incomplete.any():
        if frames is None:
            raise ArticulationError("a sensor rides rigidly on its parent and no frames place it yet")
        art = art.completed(*frames)
    names = tuple(art.names)
    art = rooted_at(art, hips)
    tree = _Tree(names, art)
    start = proximal_points(tree, hum)
    offsets = tpose_offsets(tree, hum)
    tpose = np.zeros_like(offsets)  # each body's bone start in the T-pose, relative to the hips'
    for j in art.order[1:]:
        tpose[j] = tpose[art.parent[j]] + offsets[j]
    sensor = np.array([-1 if hum.sensor(b) is None else hum.sensor(b) for b in BONES])
    bone_of = np.full(len(names), -1)
    bone_of[sensor[sensor >= 0]] = np.flatnonzero(sensor >= 0)
    parent_bone = np.full(len(BONES), -1)
    local = np.zeros((len(BONES), 3))
    for k in np.flatnonzero(sensor >= 0):
        j = art.parent[sensor[k]]
        while j >= 0 and bone_of[j] < 0:  # a body with no bone between two that have one
            j = art.parent[j]
        if j >= 0:
            parent_bone[k] = bone_of[j]
            local[k] = tpose[sensor[k]] - tpose[j]
    return HumanoidRig(names, hum, art, start, sensor, parent_bone, local)


def rooted_at(art: Articulation, root: int) -> Articulation:
    """The same bodies and joints as a tree hanging from body `root`: every joint on the way from the old
    root to it turned round (its point in the child's frame becomes the parent's and back). `art` must be
    complete (`Articulation.completed`)."""
    if art.root == root:
        return art
    m = art.n_bodies
    neighbours: list[list[int]] = [[] for _ in range(m)]
    for j in range(m):
        if art.parent[j] >= 0:
            neighbours[j].append(int(art.parent[j]))
            neighbours[int(art.parent[j])].append(j)
    parent = np.full(m, -1)
    c = np.zeros((m, 3))
    l = np.zeros((m, 3))
    order = [root]
    for i in order:  # grows while it walks: a breadth-first walk from the new root
        for j in neighbours[i]:
            if j == root or parent[j] >= 0:
                continue
            parent[j] = i
            if art.parent[j] == i:  # the joint keeps its direction
                c[j], l[j] = art.c[j], art.l[j]
            else:  # i hung from j: the joint's point in j's frame was i's `l`, in i's frame its `c`
                c[j], l[j] = art.l[i], art.c[i]
            order.append(j)
    return Articulation(art.names, parent, c, l, np.asarray(order))


class _Tree:
    """An articulation as the humanoid helpers read a calibration: names, root and the tree's joints."""

    def __init__(self, names: tuple[str, ...], art: Articulation):
        self.names, self.root = names, art.root
        child = art.order[1:]
        self._joints = (np.stack([child, art.parent[child]], axis=1), art.c[child], art.l[child])

    def joint_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return self._joints
