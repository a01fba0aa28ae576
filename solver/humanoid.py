"""Which humanoid bone each body is (VRM 1.0 names), found from the fitted tree and a sample of the take.

The tree's shape says hips, spine, chest, head, arms and legs; the data say up (where the trunk and the
legs point over the take), left and right (knees bend backward, elbows forward) and each body's T-pose
frame. Sensor names are never read, only checked against the finding (`conflicts`). docs/solver.md.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from flockcal.frames import Frames
from flockcal.frames import chunk_frames as frames_per_chunk
from flockcal.names import named_bones
from flockcal.rotations import nearest_rotation

# VRM 1.0 `humanoid.humanBones` names, in the order of the VRPN sensors (sensor k is BONES[k]).
BONES: tuple[str, ...] = (
    "hips", "spine", "chest", "head",
    "leftUpperArm", "leftLowerArm", "leftHand", "rightUpperArm", "rightLowerArm", "rightHand",
    "leftUpperLeg", "leftLowerLeg", "leftFoot", "rightUpperLeg", "rightLowerLeg", "rightFoot",
)

# What the shape test accepts, in the words every "not human" reason ends with.
HUMAN_TREE = ("a human tree is hips and chest (with or without one spine body between them), a head on the "
              "chest, two arms of three bodies on the chest and two legs of three bodies on the hips")

# The joint at each bone's inboard end, as people name it. The trunk's two joints: hips–spine is the lower
# back and spine–chest the mid back; with no spine body the one hips–chest joint spans the lumbar spine,
# the lower back.
JOINT_NAMES = {
    "spine": "lower back", "chest": "mid back", "head": "neck",
    "leftUpperArm": "left shoulder", "leftLowerArm": "left elbow", "leftHand": "left wrist",
    "rightUpperArm": "right shoulder", "rightLowerArm": "right elbow", "rightHand": "right wrist",
    "leftUpperLeg": "left hip", "leftLowerLeg": "left knee", "leftFoot": "left ankle",
    "rightUpperLeg": "right hip", "rightLowerLeg": "right knee", "rightFoot": "right ankle",
}
# How far out from the hips each bone is: a joint is named after its more distal body's bone.
_DEPTH = {"hips": 0, "spine": 1, "chest": 2, "head": 3, "leftUpperArm": 3, "rightUpperArm": 3,
          "leftLowerArm": 4, "rightLowerArm": 4, "leftHand": 5, "rightHand": 5, "leftUpperLeg": 1,
          "rightUpperLeg": 1, "leftLowerLeg": 2, "rightLowerLeg": 2, "leftFoot": 3, "rightFoot": 3}

# The sample of the take the finding reads: a frame every SAMPLE_DT_S of the take's clock, at most
# SAMPLE_CAP of them (beyond that every other one is dropped and the spacing doubles, so the sample keeps
# covering the whole take): 0.85 MB for 16 sensors.
SAMPLE_DT_S = 0.1
SAMPLE_CAP = 512

# A limb shows the plane it bends in when the angle at its middle joint varied by at least this over the
# sample (radians rms, about 6°); a limb held stiller takes the trunk's lateral axis, carried onto it by
# their mean relative rotation, for its T-pose frame; with no limb past it, left and right are not told
# apart at all (a performer standing still: the bends are then sensor geometry and noise).
MOVED_RAD = 0.1


@dataclass(frozen=True)
class NameConflict:
    """A sensor whose name says one bone where the data found another (`l_hand` found on the right forearm)."""

    sensor: int  # index into the calibration's names
    named: str  # the bone the user's name implies (a BONES entry)
    found: str  # the bone the data found (a BONES entry)


@dataclass(frozen=True, eq=False)
class Humanoid:
    """The humanoid reading of one calibration.

    `bones[i]` is sensor i's VRM 1.0 bone (a BONES entry) or None; all None when the tree is not
    human-shaped, `reason` then saying why. `world` (3, 3) turns tracker-world vectors into the humanoid's
    world: right-handed, +Y up (found from the data), +Z the performer's mean facing, +X their left (glTF's
    and VRM's axes; metres). `frames[i]` (3, 3) is body i's T-pose frame in its sensor's frame: the body's
    segment orientation in tracker world at a frame is `R_i @ frames[i]`, and `world @ R_i @ frames[i]` is
    the identity when the body is in the T-pose facing +Z (VRM's normalized rest). NaN for bodies with no bone.

    Besides: `tree`, the undirected joints (body pairs) and rigid groups it was found on, and `sample_frames`,
    how many frames the sample had taken in by then (what `humanoid_for` decides a reuse by); `evidence`,
    the figures the left/right decision rests on (docs/solver.md); `body[i]`, the sensor that stands for
    sensor i's body (itself, or for a rigid group's riding member the member with the bone).
    """

    bones: tuple
    world: np.ndarray
    frames: np.ndarray
    reason: str = ""
    conflicts: tuple = field(default_factory=tuple)  # NameConflict, …
    tree: frozenset = frozenset()
    sample_frames: int = 0
    evidence: dict = field(default_factory=dict)
    body: tuple = ()

    @property
    def human(self) -> bool:
        return not self.reason

    @property
    def posable(self) -> bool:
        """Whether it carries what poses a rig (`world`, `frames`): a human finding made from frames, or a
        tree found not human. A humanoid read back from the §5 JSON keeps the bones only."""
        return not self.human or bool(np.isfinite(self.world).all())

    def sensor(self, bone: str) -> int | None:
        """The sensor index of `bone`, or None when no body is that bone."""
        try:
            return self.bones.index(bone)
        except ValueError:
            return None

    def mapping(self, names) -> dict[str, str]:
        """{sensor name: bone} for every body with a bone."""
        return {str(names[i]): b for i, b in enumerate(self.bones) if b is not None}

    def joint_name(self, child: int, parent: int) -> str | None:
        """The anatomical name of the joint between sensors `child` and `parent` ("left knee"), whichever way
        the tree is rooted; None unless both are bodies of a human tree. A rigid member (no bone of its own)
        counts as its body."""
        if self.body:
            child, parent = self.body[child], self.body[parent]
        a, b = self.bones[child], self.bones[parent]
        if a is None or b is None:
            return None
        distal = a if _DEPTH[a] >= _DEPTH[b] else b
        if distal == "chest" and self.sensor("spine") is None:
            return JOINT_NAMES["spine"]  # hips–chest: the lumbar spine
        return JOINT_NAMES.get(distal)


# A bone in the words of a sentence ("found on the right forearm").
_BONE_WORDS = {"hips": "hips", "spine": "spine", "chest": "chest", "head": "head", "UpperArm": "upper arm",
               "LowerArm": "forearm", "Hand": "hand", "UpperLeg": "thigh", "LowerLeg": "shin", "Foot": "foot"}


def bone_words(bone: str) -> str:
    """'leftLowerArm' → 'left forearm', 'hips' → 'hips'."""
    for side in ("left", "right"):
        if bone.startswith(side):
            return f"{side} {_BONE_WORDS[bone[len(side):]]}"
    return _BONE_WORDS[bone]


def conflict_message(names, conflict: NameConflict) -> str:
    """The warning a person reads: "sensor 'l_hand' is named for the left hand but was found on the right
    forearm (the outputs follow the data)"."""
    return (f"sensor {str(names[conflict.sensor])!r} is named for the {bone_words(conflict.named)} but was found "
            f"on the {bone_words(conflict.found)} (the outputs follow the data; check the strap or the name)")


def node_name(bone: str) -> str:
    """A bone's name in PascalCase, as BVH joints and glTF nodes carry it: "leftUpperArm" → "LeftUpperArm"."""
    return bone[:1].upper() + bone[1:]


# --- the sample -------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Sample:
    """A snapshot of a `HumanoidSample`: its frames, and how many frames it had ever taken in (`seen`)."""

    frames: Frames
    seen: int


class HumanoidSample:
    """A bounded, evenly spread sample of a take's frames: one every `dt` seconds of its clock, at most `cap`;
    when full, every other frame goes and the spacing doubles. Fed a batch at a time (`add`); `frames()` is
    a snapshot that later `add`s never change (arrays are appended past it or replaced, never rewritten),
    so another thread may read it while frames keep coming. `seen` counts the frames ever taken in."""

    def __init__(self, n_sensors: int, dt: float = SAMPLE_DT_S, cap: int = SAMPLE_CAP):
        self.m = int(n_sensors)
        self.dt = float(dt)
        self.cap = max(2, int(cap) // 2 * 2)
        self._alloc(self.cap)
        self.n = 0
        self.seen = 0
        self._origin: float | None = None  # the first frame's time: the grid's zero
        self._cell = -np.inf  # the grid cell of the newest frame kept

    def _alloc(self, size: int) -> None:
        self.times = np.zeros(size)
        self.rotations = np.zeros((size, self.m, 3, 3))
        self.positions = np.zeros((size, self.m, 3))
        self.valid = np.zeros((size, self.m), dtype=bool)

    def add(self, frames: Frames) -> int:
        """Keep the frames of `frames` that fall on the sample's spacing; returns how many were kept. The
        spacing is a grid of `dt` from the first frame's time: the first frame in each cell is kept, so the
        sample depends on the frames alone, not on how they were batched."""
        ts = np.asarray(frames.times, dtype=float)
        kept, k0 = 0, 0
        while k0 < len(ts):
            if self._origin is None:
                self._origin = float(ts[k0])
            cells = np.floor((ts[k0:] - self._origin) / self.dt)
            # The first frame past the last kept cell and every frame that reaches a new one (a running max:
            # a clock that steps back enters no cell twice).
            reach = np.maximum.accumulate(np.concatenate([[self._cell], cells]))
            pick = k0 + np.flatnonzero(reach[1:] > reach[:-1])
            room = self.cap - self.n
            take = pick[:room]
            if len(take):
                v = np.asarray(frames.valid[take], dtype=bool)
                at = slice(self.n, self.n + len(take))
                self.times[at] = ts[take]
                self.rotations[at] = np.where(v[..., None, None], frames.rotations[take], 0.0)
                self.positions[at] = np.where(v[..., None], frames.positions[take], 0.0)
                self.valid[at] = v
                self.n += len(take)
                self.seen += len(take)
                kept += len(take)
                self._cell = float(cells[take[-1] - k0])
            if len(pick) <= room:
                break
            self._halve()
            k0 = int(pick[room])
        return kept

    def _halve(self) -> None:
        keep = slice(0, self.n, 2)
        old = (self.times[keep], self.rotations[keep], self.positions[keep], self.valid[keep])
        self._alloc(self.cap)  # new arrays: a snapshot of the old ones stays as it was
        k = len(old[0])
        self.times[:k], self.rotations[:k], self.positions[:k], self.valid[:k] = old
        self.n = k
        self.dt *= 2.0
        self._cell = float(np.floor((self.times[k - 1] - self._origin) / self.dt))

    def frames(self) -> Frames:
        """The sample so far (views: valid while the sample lives, never rewritten)."""
        n = self.n
        return Frames(self.times[:n], self.rotations[:n], self.positions[:n], self.valid[:n])

    def snapshot(self) -> Sample:
        """The sample so far, for a fit on another thread (no copy: see the class)."""
        return Sample(self.frames(), self.seen)


def take_sample(take, dt: float = SAMPLE_DT_S, cap: int = SAMPLE_CAP, chunk_frames: int | None = None) -> HumanoidSample:
    """The sample of a `flockcal.takes.ChunkedTake` (a Take, a take file, or the service's frame log), read
    through its `chunks` (None: `flockcal.frames.chunk_frames`, about 8 MB of arrays, which keeps a take
    file's memory to its budget; the sample does not depend on them): what `flockcal fit` and the exports
    find the humanoid from, as the service does from its frames."""
    sample = HumanoidSample(len(take.names), dt, cap)
    for f in take.chunks(chunk_frames or frames_per_chunk(len(take.names))):
        sample.add(f)
    return sample


# --- the finding ------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class _Shape:
    """The bodies of a human tree by role (sensor indices; spine −1 when there is none)."""

    hips: int
    spine: int
    chest: int
    head: int
    arms: tuple  # two (upper, lower, hand)
    legs: tuple  # two (upper, lower, foot)


def tree_key(cal) -> frozenset:
    """The tree as the finding sees it: its joints as unordered sensor pairs, and its rigid groups."""
    pairs = cal.joints.pairs
    return frozenset([frozenset(map(int, p)) for p in pairs.tolist()]
                     + [("rigid", tuple(sorted(map(int, g)))) for g in cal.rigid_groups])


def _body_of(cal) -> np.ndarray:
    """(m,) the sensor that stands for each sensor's body: itself, or for a rigid member the member its
    group hangs from (the tree hangs rigid members from that sensor, with no joint of their own)."""
    m = len(cal.names)
    is_joint = np.zeros(m, dtype=bool)
    is_joint[cal.joints.pairs[:, 0]] = True
    rep = np.arange(m)
    for i in np.asarray(cal.order).tolist():
        p = int(cal.parent[i])
        if p >= 0 and not is_joint[i]:
            rep[i] = rep[p]
    return rep


def tree_shape(cal) -> tuple[_Shape | None, str]:
    """The roles of a human-shaped tree, or (None, why not) in a sentence for a user."""
    rep = _body_of(cal)
    bodies = sorted(set(rep.tolist()))
    nbrs: dict[int, set] = {b: set() for b in bodies}
    for c, p in cal.joints.pairs.tolist():
        a, b = int(rep[c]), int(rep[p])
        if a != b:
            nbrs[a].add(b)
            nbrs[b].add(a)
    n = len(bodies)
    if n not in (15, 16):
        what = f"{n} bodies" + (f" (of {len(rep)} sensors: some move rigidly together)" if n != len(rep) else "")
        return None, f"not a human tree: it has {what}; {HUMAN_TREE} (15 or 16 bodies)"
    branch = [b for b in bodies if len(nbrs[b]) >= 3]
    if len(branch) != 2:
        return None, (f"not a human tree: {len(branch)} bodies branch (carry three or more neighbours), a human "
                      f"tree has two, the hips and the chest; {HUMAN_TREE}")
    a, b = branch
    spine = -1
    if b not in nbrs[a]:
        between = [x for x in nbrs[a] & nbrs[b] if len(nbrs[x]) == 2]
        if len(between) != 1:
            return None, f"not a human tree: its two branching bodies are not joined through at most one body; {HUMAN_TREE}"
        spine = between[0]
    trunk = {a, b, spine}
    chains = {}
    for x in (a, b):
        out = []
        for start in sorted(nbrs[x] - trunk):
            chain, prev, cur = [start], x, start
            while len(nbrs[cur]) == 2:
                prev, cur = cur, next(iter(nbrs[cur] - {prev}))
                chain.append(cur)
            out.append(chain)
        chains[x] = out
    lengths = {x: sorted(len(c) for c in chains[x]) for x in (a, b)}
    chest = next((x for x in (a, b) if lengths[x] == [1, 3, 3]), None)
    hips = next((x for x in (a, b) if lengths[x] == [3, 3] and x != chest), None)
    if chest is None or hips is None:
        said = " and ".join(f"{'+'.join(map(str, lengths[x])) or 'nothing'}" for x in (a, b))
        return None, (f"not a human tree: its branching bodies carry chains of {said} bodies, where the chest "
                      f"carries 1+3+3 (head and arms) and the hips 3+3 (legs); {HUMAN_TREE}")
    head = next(c[0] for c in chains[chest] if len(c) == 1)
    arms = tuple(tuple(c) for c in chains[chest] if len(c) == 3)
    legs = tuple(tuple(c) for c in chains[hips])
    return _Shape(hips, spine, chest, head, arms, legs), ""


class _Points:
    """The sample's frames and every tree joint's centre in the world at each: the fitted centre, or where
    nothing turned about the joint beyond noise its child's sensor (the fit's point is then the minimum-norm
    point of a pair that never moved)."""

    def __init__(self, cal, R: np.ndarray, t: np.ndarray, valid: np.ndarray, toward: dict):
        self.R, self.t, self.valid = R, t, valid
        self._relative: dict = {}
        self.toward = toward  # body → its neighbour toward the trunk (the tree may hang from any body)
        pairs, c, l = cal.joint_arrays()
        rep = _body_of(cal)
        self.row = {frozenset((int(rep[a]), int(rep[b]))): k for k, (a, b) in enumerate(pairs.tolist())}
        ci, pi = pairs[:, 0], pairs[:, 1]
        # A centre counts where the joint turned beyond noise about some direction (rank > 3): the fit solved
        # it along those and holds its minimum-norm point along the rest, which stays nearer the joint than
        # a sensor (a foot sensor sits centimetres in front of the ankle: the legs' frames were 57° off with
        # the sensors of every undetermined joint, 15° with these centres; docs/solver.md).
        fitted = (np.asarray(cal.joints.rank) > 3) & np.isfinite(c).all(axis=1) & np.isfinite(l).all(axis=1)
        J = cal.joints
        self.hinges = {frozenset((int(a), int(b))): {int(a): J.axis_i[k], int(b): J.axis_j[k]}
                       for k, (a, b) in enumerate(pairs.tolist())
                       if J.hinge[k] and np.isfinite(J.axis_i[k]).all() and np.isfinite(J.axis_j[k]).all()}
        c0, l0 = np.where(fitted[:, None], c, 0.0), np.where(fitted[:, None], l, 0.0)
        # Halfway between the two bodies' own places for the centre: the residual split between them.
        self.both = 0.5 * (np.einsum("njab,jb->nja", R[:, ci], c0) + t[:, ci]
                           + np.einsum("njab,jb->nja", R[:, pi], l0) + t[:, pi])  # (n, J, 3)
        self.both_ok = valid[:, ci] & valid[:, pi]  # (n, J)
        self.fitted = fitted

    def joint(self, body: int) -> tuple[np.ndarray, np.ndarray]:
        """(n, 3) the world place of `body`'s joint toward the trunk at every frame, (n,) where it is seen:
        the fitted centre, or the body's own sensor where nothing turned about the joint."""
        k = self.row[frozenset((int(body), int(self.toward[body])))]
        if self.fitted[k]:
            return self.both[:, k], self.both_ok[:, k]
        return self.t[:, body], self.valid[:, body]

    def sum_in(self, body: int, v: np.ndarray, ok: np.ndarray) -> np.ndarray:
        """Σ over the frames `ok` (where `body` is seen too) of world vectors v (n, 3), in `body`'s frame."""
        ok = ok & self.valid[:, body]
        return np.einsum("nji,nj->i", self.R[ok, body], v[ok])

    def relative(self, a: int, b: int) -> np.ndarray:
        """Body b's mean rotation in body a's frame over the frames both are seen (the identity if never)."""
        if (a, b) not in self._relative and (b, a) not in self._relative:
            self.prefetch([(a, b)])
        return self._relative[a, b] if (a, b) in self._relative else self._relative[b, a].T

    def prefetch(self, pairs) -> None:
        """Work out `relative` for many pairs (a, b) at once: one product over the frames, one projection."""
        pairs = np.asarray(pairs, dtype=int).reshape(-1, 2)
        a, b = pairs[:, 0], pairs[:, 1]
        w = (self.valid[:, a] & self.valid[:, b]).astype(float)  # (n, k)
        count = w.sum(axis=0)
        mean = np.einsum("nk,nkji,nkjl->kil", w, self.R[:, a], self.R[:, b]) / np.maximum(count, 1.0)[:, None, None]
        rel = np.where((count > 0)[:, None, None], nearest_rotation(np.where((count > 0)[:, None, None], mean, np.eye(3))),
                       np.eye(3))
        for k, (x, y) in enumerate(pairs.tolist()):
            self._relative[x, y] = rel[k]


@dataclass(frozen=True)
class _Bend:
    """One limb's bending over the sample: (proximal − middle) × (distal − middle) per frame (world), where
    it is seen, the angle between the two segments, and its spread."""

    s: np.ndarray  # (n, 3)
    ok: np.ndarray  # (n,)
    angle: np.ndarray  # (n,) radians, π when straight
    moved: float  # the angle's standard deviation over the frames seen (radians)

    @staticmethod
    def of(pts: _Points, chain) -> "_Bend":
        (P, okp), (M, okm), (D, okd) = (pts.joint(x) for x in chain)
        a, b = P - M, D - M
        ok = okp & okm & okd
        s = np.where(ok[:, None], np.cross(a, b), 0.0)
        scale = np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1)
        cos = np.einsum("ni,ni->n", a, b) / np.where(scale > 0, scale, 1.0)
        angle = np.arccos(np.clip(cos, -1.0, 1.0))
        return _Bend(s, ok, angle, float(angle[ok].std()) if ok.sum() > 1 else 0.0)

    def evidence(self, pts: _Points, body: int) -> np.ndarray:
        """The bending summed in `body`'s frame, weighted by how far the limb moved: a limb held still shows
        only where its sensors sit (a constant bend of either sign), not the way it bends."""
        return self.moved * pts.sum_in(body, self.s, self.ok)


def _unit(v: np.ndarray) -> np.ndarray:
    """Unit vectors along the last axis (zero stays zero)."""
    n = np.sqrt(np.einsum("...i,...i->...", v, v))[..., None]
    return np.where(n > 0, v / np.where(n > 0, n, 1.0), 0.0)


def _frame(primary: np.ndarray, secondary: np.ndarray, order: str) -> np.ndarray:
    """Columns (X, Y, Z) of a right-handed frame: `primary` exactly along the axis `order` names ("x" or
    "y"), `secondary` made orthogonal to it along the other."""
    p = _unit(primary)
    s = _unit(secondary - (secondary @ p) * p)
    if order == "x":
        x, y = p, s
    else:
        x, y = s, p
    return np.column_stack([x, y, np.cross(x, y)])


def _empty(m: int, reason: str, tree=frozenset(), seen: int = 0) -> Humanoid:
    return Humanoid((None,) * m, np.full((3, 3), np.nan), np.full((m, 3, 3), np.nan), reason, (), tree, seen)


def find_humanoid(cal, rotations: np.ndarray, positions: np.ndarray, valid: np.ndarray | None = None,
                  *, sample_frames: int | None = None) -> Humanoid:
    """The humanoid bone of every body of `cal`, from its tree and a sample of the take's frames
    (`rotations` (n, m, 3, 3), `positions` (n, m, 3), `valid` (n, m)); `sample_frames`: how many frames the
    sample had taken in (`HumanoidSample.seen`; default n), kept for `humanoid_for`.

    Roles from the tree's shape (`tree_shape`); up as the mean, over the sample, of the direction from the
    hips sensor to the head sensor and from the feet sensors to the hips sensor; left and right from the
    knees' and elbows' bending: (hip − knee) × (ankle − knee) points to the performer's right and
    (shoulder − elbow) × (wrist − elbow) to their left, in proportion to the sine of the bend; summed in the
    hips' and the chest's frames, each limb weighted by how far it moved, they give the lateral axis the two
    hips' and the two shoulders' places are read along. docs/solver.md says the rules and their limits."""
    names = tuple(cal.names)
    m = len(names)
    R = np.asarray(rotations, dtype=float)
    t = np.asarray(positions, dtype=float)
    n = R.shape[0]
    valid = np.ones((n, m), dtype=bool) if valid is None else np.asarray(valid, dtype=bool)
    finite = np.isfinite(t).all(axis=2) & np.isfinite(R).all(axis=(2, 3))
    if not (finite | ~valid).all():  # a sample's invalid slots hold zeros already; anything else is cleaned
        valid = valid & finite
        R = np.where(valid[..., None, None], R, 0.0)
        t = np.where(valid[..., None], t, 0.0)
    seen = n if sample_frames is None else int(sample_frames)
    key = tree_key(cal)
    shape, why = tree_shape(cal)
    if shape is None:
        return _empty(m, why, key, seen)
    if n < 2 or valid.sum(axis=0).min(initial=n) < 2:
        return _empty(m, "no frames of the take to find the humanoid from yet", key, seen)
    h, ch = shape.hips, shape.chest
    toward = {ch: shape.spine if shape.spine >= 0 else h, shape.head: ch}
    if shape.spine >= 0:
        toward[shape.spine] = h
    for trunk, chains in ((ch, shape.arms), (h, shape.legs)):
        for chain in chains:
            toward.update(zip(chain, (trunk,) + tuple(chain[:-1])))
    pts = _Points(cal, R, t, valid, toward)
    up = _up(shape, t, valid)
    # The mean relative rotations the frames below read, in one pass: trunk, and each leaf to its parent.
    pts.prefetch([(h, ch)] + ([(shape.spine, h), (shape.spine, ch)] if shape.spine >= 0 else [])
                 + [(ch, shape.head)] + [(c[1], c[2]) for c in shape.arms + shape.legs])

    legs = [_Bend.of(pts, c) for c in shape.legs]
    arms = [_Bend.of(pts, c) for c in shape.arms]
    right_h = sum(b.evidence(pts, h) for b in legs)  # a leg's bending points right
    arms_left = sum(b.evidence(pts, ch) for b in arms)  # an arm's points left
    Q = pts.relative(h, ch)  # the chest's mean rotation in the hips' frame
    left_h = Q @ arms_left - right_h
    if max(b.moved for b in legs + arms) < MOVED_RAD or not np.linalg.norm(left_h) > 0:
        return _empty(m, f"no knee or elbow bent by {np.degrees(MOVED_RAD):.0f}° rms yet, which is what tells left "
                         "from right: bend the knees and elbows", key, seen)
    left_h = _unit(left_h)
    left_c = Q.T @ left_h

    def side_line(chains, body):
        """Σ over frames of the first limb's proximal joint minus the second's, in `body`'s frame."""
        (p0, ok0), (p1, ok1) = pts.joint(chains[0][0]), pts.joint(chains[1][0])
        return pts.sum_in(body, p0 - p1, ok0 & ok1)

    hip_line = side_line(shape.legs, h)
    shoulder_line = side_line(shape.arms, ch)
    legs_lr = shape.legs if hip_line @ left_h > 0 else shape.legs[::-1]  # (left, right)
    arms_lr = shape.arms if shoulder_line @ left_c > 0 else shape.arms[::-1]
    evidence = {
        "legs_moved_deg": [round(float(np.degrees(b.moved)), 2) for b in legs],
        "arms_moved_deg": [round(float(np.degrees(b.moved)), 2) for b in arms],
        "legs_arms_agree": _cos(-right_h, Q @ arms_left),
        "hip_line": _cos(hip_line, left_h), "shoulder_line": _cos(shoulder_line, left_c),
    }

    bones: list = [None] * m
    for b, i in (("hips", h), ("spine", shape.spine), ("chest", ch), ("head", shape.head)):
        if i >= 0:
            bones[i] = b
    for side, arm, leg in zip(("left", "right"), arms_lr, legs_lr):
        for b, i in zip(("UpperArm", "LowerArm", "Hand"), arm):
            bones[i] = side + b
        for b, i in zip(("UpperLeg", "LowerLeg", "Foot"), leg):
            bones[i] = side + b

    bends = dict(zip(shape.legs + shape.arms, legs + arms))
    frames = _tpose_frames(shape, pts, up, left_h, left_c, legs_lr, arms_lr, bends)
    world = _world(pts, h, frames[h], up)
    conflicts = tuple(NameConflict(i, named, bones[i]) for i in range(m) if bones[i] is not None
                      for named in [_named(names[i], bones[i])] if named is not None)
    return Humanoid(tuple(bones), world, frames, "", conflicts, key, seen, evidence,
                    tuple(int(x) for x in _body_of(cal)))


def _cos(a: np.ndarray, b: np.ndarray) -> float | None:
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    return round(float(a @ b / (na * nb)), 4) if na * nb > 0 else None


def _up(shape: _Shape, t: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Up in the tracker's world: the mean over the sample of the unit directions hips sensor → head sensor
    and feet sensors → hips sensor (a magnetic tracker knows no gravity; a performer's trunk and legs do)."""
    h, hd = shape.hips, shape.head
    feet = [leg[2] for leg in shape.legs]
    ok1 = valid[:, h] & valid[:, hd]
    ok2 = valid[:, h] & valid[:, feet[0]] & valid[:, feet[1]]
    v = _unit(t[ok1, hd] - t[ok1, h]).sum(axis=0)
    v = v + _unit(t[ok2, h] - 0.5 * (t[ok2, feet[0]] + t[ok2, feet[1]])).sum(axis=0)
    return _unit(v)


def _tpose_frames(shape: _Shape, pts: _Points, up, left_h, left_c, legs_lr, arms_lr, bends) -> np.ndarray:
    """(m, 3, 3) each body's T-pose frame in its sensor frame (the `Humanoid.frames` convention): the trunk's
    Y the found up as each body holds it on average, X its lateral axis; a limb segment's long axis from its
    inboard to its outboard joint, its other axis from the limb's bending (or, for a limb that hardly bent,
    the trunk's lateral axis carried over by their mean relative rotation); a leaf (hand, foot, head) its
    parent's frame at its mean pose relative to the parent."""
    m = pts.R.shape[1]
    frames = np.full((m, 3, 3), np.nan)
    h, ch = shape.hips, shape.chest

    def mean_up(body):
        ok = pts.valid[:, body]
        return np.einsum("nji,j->i", pts.R[ok, body], up)

    frames[h] = _frame(mean_up(h), left_h, "y")
    frames[ch] = _frame(mean_up(ch), left_c, "y")
    if shape.spine >= 0:
        s = shape.spine
        frames[s] = _frame(mean_up(s), pts.relative(s, h) @ left_h + pts.relative(s, ch) @ left_c, "y")

    def long_axis(body, distal):
        """The mean, in `body`'s frame, of its outboard joint (`distal`'s inboard one) minus its inboard one."""
        (a, oka), (b, okb) = pts.joint(body), pts.joint(distal)
        return pts.sum_in(body, b - a, oka & okb)

    def lateral(chain, body, trunk_axis):
        """(the limb's bending axis in `body`'s frame, pointing as its bending cross product does: right for
        a leg, left for an arm; whether it is a hinge's). A determined hinge's axis at its middle joint, else
        the bending summed over the frames where the limb moved, else the trunk's lateral axis carried over
        by the mean pose."""
        bend = bends[chain]
        moved = bend.moved >= MOVED_RAD
        summed = pts.sum_in(body, bend.s, bend.ok) if moved else trunk_axis(body)
        axis = pts.hinges.get(frozenset(chain[:2]), {}).get(body)
        if axis is None:
            return summed, False
        return (axis if axis @ summed >= 0 else -axis), True

    def from_hips(body):
        return -(pts.relative(body, h) @ left_h)  # right, as a leg's bending points

    def from_chest(body):
        return pts.relative(body, ch) @ left_c

    # A hinge's axis is the segment's surest axis: the far joint's place along it is what soft tissue moves
    # most (an ankle's centre along the knee's axis, docs/design.md §3c), so it leads where there is one.
    for leg in legs_lr:
        for body, distal in ((leg[0], leg[1]), (leg[1], leg[2])):
            # Hip → knee → ankle: down in the T-pose; the bending points right.
            side, hinge = lateral(leg, body, from_hips)
            down = long_axis(body, distal)
            frames[body] = _frame(-side, -down, "x") if hinge else _frame(-down, -side, "y")
    for sign, arm in zip((1.0, -1.0), arms_lr):
        for body, distal in ((arm[0], arm[1]), (arm[1], arm[2])):
            # Shoulder → elbow → wrist: +X for the left arm in the T-pose, −X for the right; the bending
            # points left while the arm hangs, up once it is raised to the T-pose.
            side, hinge = lateral(arm, body, from_chest)
            out = long_axis(body, distal)
            frames[body] = _frame(sign * side, sign * out, "y") if hinge else _frame(sign * out, sign * side, "x")
    for leaf, par in [(shape.head, ch)] + [(c[2], c[1]) for c in shape.arms + shape.legs]:
        frames[leaf] = pts.relative(par, leaf).T @ frames[par]
    return frames


# If the performer's facing over the sample averages to less than this (a walk round a loop), the world's
# +Z is their facing at the sample's first frame instead.
FACING_RESULTANT = 0.3


def _world(pts: _Points, h: int, frame_h: np.ndarray, up: np.ndarray) -> np.ndarray:
    """Tracker world → humanoid world: rows left, up, forward; forward the hips' mean facing, level."""
    ok = pts.valid[:, h]
    fwd = pts.R[ok, h] @ frame_h[:, 2]
    fwd = _unit(fwd - (fwd @ up)[:, None] * up)
    mean = fwd.mean(axis=0)
    if np.linalg.norm(mean) < FACING_RESULTANT and len(fwd):
        mean = fwd[0]
    fwd = _unit(mean - (mean @ up) * up)
    return np.stack([np.cross(up, fwd), up, fwd])


def _named(name: str, found: str) -> str | None:
    """The bone `name` implies where it contradicts `found` (a BONES entry), else None. A name that
    implies several bones ("left leg", "forearm") contradicts only a bone outside them, and is reported as
    the one of them most like `found`."""
    implied = named_bones(name)
    if not implied or found in implied:
        return None
    for bone in implied:  # the same segment on the other side first
        if bone.removeprefix("left").removeprefix("right") == found.removeprefix("left").removeprefix("right"):
            return bone
    return implied[0]


def humanoid_for(cal, sample: Sample | None, previous: Humanoid | None = None, regrow: float = 1.25) -> Humanoid | None:
    """The humanoid of `cal`: `previous` again when it was found on the same tree and the sample has taken in
    fewer than `regrow` times the frames it had then (the live service refits ~30 times a second; the tree
    and the performer's way of moving do not change that fast, and a growing sample is looked at again at
    1.25, 1.56, 1.95, … times its size), else found afresh from `sample`. None without either."""
    if previous is not None and previous.tree == tree_key(cal) and (
            sample is None or sample.seen < regrow * max(previous.sample_frames, 1)):
        return previous
    if sample is None:
        return None
    f = sample.frames
    return find_humanoid(cal, f.rotations, f.positions, f.valid, sample_frames=sample.seen)


# --- what the outputs read --------------------------------------------------------------------------------

def proximal_points(cal, hum: Humanoid) -> np.ndarray:
    """(m, 3) where each body's bone starts, in its own sensor frame: its inboard joint's centre (`c`), and
    for the root the midpoint of its two hip joints when both upper legs hang from it (the hips' centre on a
    human tree rooted at the hips), else the mean of its outboard joints' centres (`l`)."""
    m = len(cal.names)
    pts = np.full((m, 3), np.nan)
    pairs, c, l = cal.joint_arrays()
    pts[pairs[:, 0]] = c
    at_root = pairs[:, 1] == cal.root
    if hum.human and hum.bones[cal.root] == "hips":
        # The hips' bone starts between the two hip joints, not at the mean with the lower back's.
        legs = np.array([hum.bones[i] in ("leftUpperLeg", "rightUpperLeg") for i in pairs[:, 0]], dtype=bool)
        if (at_root & legs).sum() == 2:
            at_root = at_root & legs
    if at_root.any():
        pts[cal.root] = l[at_root].mean(axis=0)
    return pts


def tpose_offsets(cal, hum: Humanoid) -> np.ndarray:
    """(m, 3) each body's bone start relative to its parent's, in the T-pose, on the humanoid's world axes
    (+X the performer's left, +Y up, +Z forward; metres). Zero at the root."""
    pairs, c, l = cal.joint_arrays()
    start = proximal_points(cal, hum)
    out = np.zeros((len(cal.names), 3))
    child, parent = pairs[:, 0], pairs[:, 1]
    v = l - start[parent]  # in the parent's sensor frame
    # In the T-pose, world @ R_p @ frames[p] = I, so the parent's sensor axes read on the world's are frames[p]ᵀ.
    out[child] = np.einsum("kji,kj->ki", hum.frames[parent], v)
    return out


def segment_rotations(hum: Humanoid, rotations: np.ndarray) -> np.ndarray:
    """(n, m, 3, 3) every body's segment orientation on the humanoid's world axes (the identity in the
    T-pose facing +Z), from sensor rotations (n, m, 3, 3) body → tracker world."""
    return hum.world @ np.asarray(rotations) @ hum.frames


def bones_of(names: Sequence[str], mapping) -> tuple:
    """`Humanoid.bones` from a {sensor name: bone} map (a §5 JSON's `humanoid`), None where it has none."""
    mapping = dict(mapping or {})
    return tuple(mapping.get(str(x)) if mapping.get(str(x)) in BONES else None for x in names)
