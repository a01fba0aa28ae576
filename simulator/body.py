"""Articulated bodies for the simulator: a human of 15–16 rigid bodies, the paper's wooden linkage and
its rigid sensor pair, each with one sensor per body, plus forward kinematics and the ground truth
(joint centres in the sensor frames, bone lengths) in the shape of `flockcal fit --json`.

Bone frames follow the transmitter's axes at rest (+X forward, +Y right, +Z down); a bone frame's
origin is the body's inboard joint (the root's is the hip centre). Rest pose: standing, arms at sides.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from itertools import combinations

import numpy as np

from flockcal.errors import FlockcalError
from flockcal.rotations import axis_angle, random_rotations, rot_z


class SimulatorError(FlockcalError, ValueError):
    """Bad simulator input (an unknown body, routine or fault); the message names the fix."""


@dataclass(frozen=True)
class BodyModel:
    """A tree of rigid bodies with one sensor each; arrays over the m bodies, parents before children.

    joint_offset[i]: joint i (body i's inboard joint) in the parent's bone frame (zero at the root).
    sensor_offset[i], sensor_rotation[i]: the sensor's origin and axes (sensor → bone) in body i's frame.
    joint_type[i]: 'root', 'ball', 'hinge' or 'rigid'. hinge_axis[i]: unit axis (same in parent and child
    bone frames), zero unless a hinge. limits[i, k] = (low, high) radians: for a ball joint the range of
    rotation-vector component k (about the parent bone frame's x, y, z); for a hinge, row 0 is the
    angle range about hinge_axis and rows 1–2 are zero. rest[i]: the rest coordinates, same layout.
    home_position/home_rotation: where the root stands at rest, in the transmitter frame.
    """

    names: tuple[str, ...]
    parent: np.ndarray
    joint_offset: np.ndarray
    sensor_offset: np.ndarray
    sensor_rotation: np.ndarray
    joint_type: tuple[str, ...]
    hinge_axis: np.ndarray
    limits: np.ndarray
    rest: np.ndarray
    home_position: np.ndarray
    home_rotation: np.ndarray
    kind: str = "human"
    height: float = 0.0
    extra: dict = field(default_factory=dict)

    @property
    def m(self) -> int:
        return len(self.names)

    @property
    def root(self) -> int:
        return int(np.flatnonzero(self.parent < 0)[0])

    def index(self, name: str) -> int:
        try:
            return self.names.index(name)
        except ValueError:
            raise SimulatorError(f"no body named {name!r} (this model has: {', '.join(self.names)})") from None

    def children(self, i: int) -> list[int]:
        return [int(k) for k in np.flatnonzero(self.parent == i)]

    def dofs(self, i: int) -> int:
        return {"root": 0, "rigid": 0, "hinge": 1, "ball": 3}[self.joint_type[i]]

    def subset(self, names) -> "BodyModel":
        """The model restricted to `names` (kept in this model's order); they must form a connected tree."""
        keep = sorted({self.index(n) for n in names})
        kept = set(keep)
        roots = [i for i in keep if self.parent[i] not in kept]
        if len(roots) != 1:
            raise SimulatorError(
                f"bodies {', '.join(names)} do not form one connected tree; "
                "include each chosen body's parent (e.g. take the first N in the model's order)"
            )
        if roots[0] != self.root:
            raise SimulatorError(f"a subset must contain the root body {self.names[self.root]!r}")
        new_index = {old: new for new, old in enumerate(keep)}
        parent = np.array([new_index.get(int(self.parent[i]), -1) for i in keep])
        pick = np.array(keep)
        return replace(
            self,
            names=tuple(self.names[i] for i in keep),
            parent=parent,
            joint_offset=self.joint_offset[pick],
            sensor_offset=self.sensor_offset[pick],
            sensor_rotation=self.sensor_rotation[pick],
            joint_type=tuple(self.joint_type[i] for i in keep),
            hinge_axis=self.hinge_axis[pick],
            limits=self.limits[pick],
            rest=self.rest[pick],
        )

    def joint_in_sensor_frames(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """(c, l): joint i's centre in body i's sensor frame and in its parent's sensor frame."""
        p = int(self.parent[i])
        c = self.sensor_rotation[i].T @ (np.zeros(3) - self.sensor_offset[i])
        l = self.sensor_rotation[p].T @ (self.joint_offset[i] - self.sensor_offset[p])
        return c, l

    def bones(self) -> list[dict]:
        """Joint-to-joint distances per body, defined as in design.md §5 (never sensor-to-joint)."""
        out = []
        for j in range(self.m):
            kids = self.children(j)
            if self.parent[j] >= 0:
                for k in kids:
                    out.append(_bone(self.names[j], self.names[j], self.names[k], np.linalg.norm(self.joint_offset[k])))
            else:
                for a, b in combinations(kids, 2):
                    d = np.linalg.norm(self.joint_offset[a] - self.joint_offset[b])
                    out.append(_bone(self.names[j], self.names[a], self.names[b], d))
        return out

    def truth(self) -> dict:
        """Ground truth shaped like `flockcal fit --json` (design.md §5): root, parent map, joints, bones."""
        joints = []
        for i in range(self.m):
            p = int(self.parent[i])
            if p < 0:
                continue
            c, l = self.joint_in_sensor_frames(i)
            hinge = self.joint_type[i] == "hinge"
            axis = self.hinge_axis[i]
            joints.append(
                {
                    "child": self.names[i],
                    "parent": self.names[p],
                    "type": self.joint_type[i],
                    "c": c.tolist(),
                    "l": l.tolist(),
                    "hinge": hinge,
                    "axis_child": (self.sensor_rotation[i].T @ axis).tolist() if hinge else None,
                    "axis_parent": (self.sensor_rotation[p].T @ axis).tolist() if hinge else None,
                    "limits_rad": self.limits[i, : self.dofs(i)].tolist(),
                }
            )
        return {
            "model": self.kind,
            "sensors": list(self.names),
            "root": self.names[self.root],
            "parent": {self.names[i]: self.names[p] for i, p in enumerate(self.parent) if p >= 0},
            "joints": joints,
            "bones": self.bones(),
            "height_m": self.height,
            **self.extra,
        }


def _bone(body: str, from_joint: str, to_joint: str, length: float) -> dict:
    return {"body": body, "from_joint": from_joint, "to_joint": to_joint, "length_m": float(length), "stderr_m": 0.0}


# ----------------------------------------------------------------------------------------------
# Forward kinematics


def bone_poses(model: BodyModel, local_rotations: np.ndarray, root_translation: np.ndarray):
    """Global bone poses (B (n,m,3,3), b (n,m,3)) from local rotations (n,m,3,3) and root position (n,3).

    local_rotations[:, i] rotates body i's bone frame relative to its parent's; at the root it is the
    root's global rotation. One batched product per body, vectorised over frames.
    """
    L = np.asarray(local_rotations, dtype=float)
    n = L.shape[0]
    B = np.empty((n, model.m, 3, 3))
    b = np.empty((n, model.m, 3))
    for i in range(model.m):
        p = int(model.parent[i])
        if p < 0:
            B[:, i] = L[:, i]
            b[:, i] = root_translation
        else:
            B[:, i] = B[:, p] @ L[:, i]
            b[:, i] = b[:, p] + B[:, p] @ model.joint_offset[i]
    return B, b


def sensor_poses(model: BodyModel, motion_or_rotations, root_translation: np.ndarray | None = None):
    """Exact sensor poses (rotations (n,m,3,3) sensor→world, positions (n,m,3)) for a Motion or arrays."""
    if root_translation is None:
        L, r = motion_or_rotations.local_rotations, motion_or_rotations.root_translation
    else:
        L, r = motion_or_rotations, root_translation
    B, b = bone_poses(model, L, r)
    R = B @ model.sensor_rotation
    t = b + np.einsum("nmij,mj->nmi", B, model.sensor_offset)
    return R, t


def joint_positions(model: BodyModel, local_rotations: np.ndarray, root_translation: np.ndarray) -> np.ndarray:
    """World position (n, m, 3) of every body's inboard joint (the root's bone origin at the root)."""
    return bone_poses(model, local_rotations, root_translation)[1]


# ----------------------------------------------------------------------------------------------
# Human

# Tree order, parents first. 16 bodies; the 15-body model makes the abdomen rigid with the pelvis.
HUMAN_NAMES = (
    "pelvis", "abdomen", "chest", "head",
    "l_upper_arm", "l_forearm", "l_hand", "r_upper_arm", "r_forearm", "r_hand",
    "l_thigh", "l_shin", "l_foot", "r_thigh", "r_shin", "r_foot",
)  # fmt: skip
HUMAN_PARENTS = {
    "abdomen": "pelvis", "chest": "abdomen", "head": "chest",
    "l_upper_arm": "chest", "l_forearm": "l_upper_arm", "l_hand": "l_forearm",
    "r_upper_arm": "chest", "r_forearm": "r_upper_arm", "r_hand": "r_forearm",
    "l_thigh": "pelvis", "l_shin": "l_thigh", "l_foot": "l_shin",
    "r_thigh": "pelvis", "r_shin": "r_thigh", "r_foot": "r_shin",
}  # fmt: skip
# Which bodies get sensors when fewer than 16 are asked for: each one's parent comes earlier, so any
# prefix is a connected tree of real joints (the abdomen only counts in the full 16-body suit).
HUMAN_PRIORITY = (
    "pelvis", "chest", "head", "l_upper_arm", "l_forearm", "l_hand", "r_upper_arm", "r_forearm", "r_hand",
    "l_thigh", "l_shin", "l_foot", "r_thigh", "r_shin", "r_foot", "abdomen",
)  # fmt: skip

# Joint ranges as rotation-vector components about the parent's x (roll / ab-adduction), y (flexion),
# z (twist), written for the LEFT side; the right side mirrors x and z. Radians. Signs: about +y a
# downward segment swings forward, an upward one (trunk, head) tips back.
_BALL_LIMITS = {
    "abdomen": [(-0.35, 0.35), (-0.7, 0.35), (-0.45, 0.45)],
    "chest": [(-0.3, 0.3), (-0.5, 0.25), (-0.5, 0.5)],
    "head": [(-0.6, 0.6), (-0.9, 0.6), (-1.2, 1.2)],
    "upper_arm": [(-0.3, 1.9), (-0.7, 2.2), (-1.0, 1.0)],
    "hand": [(-0.35, 0.35), (-1.0, 1.0), (-1.0, 1.0)],
    "thigh": [(-0.3, 0.7), (-0.35, 1.7), (-0.6, 0.6)],
    "foot": [(-0.35, 0.35), (-0.8, 0.35), (-0.35, 0.35)],
}
_HINGE_LIMITS = {"forearm": (0.05, 2.4), "shin": (-2.3, -0.05)}
_HINGE_REST = {"forearm": 0.25, "shin": -0.12}


def segment(name: str) -> str:
    return name[2:] if name[:2] in ("l_", "r_") else name


def human(height: float = 1.75, seed: int = 0, variation: float = 0.05, n_bodies: int = 16) -> BodyModel:
    """A standing human of `height` metres with per-subject variation (relative std of segment lengths).

    n_bodies=16 is the full suit (pelvis root, abdomen, chest, head, arms, hands, legs, feet); 15 makes
    the abdomen rigid with the pelvis; fewer keeps the first n bodies of HUMAN_PRIORITY.
    """
    if not 2 <= int(n_bodies) <= 16:
        raise SimulatorError(f"a human has 2 to 16 bodies with sensors, not {n_bodies}")
    if not 0.5 <= height <= 2.5:
        raise SimulatorError(f"height {height} m is not a plausible person; give metres, e.g. 1.75")
    if not 0.0 <= variation <= 0.3:
        raise SimulatorError(f"variation {variation} should be a relative spread between 0 and 0.3")
    rng = np.random.default_rng([int(seed), 0x50D1])
    H, s = float(height), float(height) / 1.75

    def factor(spread=1.0):
        return 1.0 + variation * spread * float(np.clip(rng.normal(), -2.0, 2.0))

    f = {k: factor() for k in ("trunk", "neck", "shoulder", "hip", "upper_arm", "forearm", "hand", "thigh", "shin", "foot")}
    side = {(k, sd): f[k] * factor(0.2) for k in ("upper_arm", "forearm", "hand", "thigh", "shin", "foot") for sd in "lr"}

    def length(seg, name):
        return side[(seg, name[0])] if (seg, name[0]) in side else f[seg]

    names = HUMAN_NAMES
    m = len(names)
    idx = {n: i for i, n in enumerate(names)}
    parent = np.array([idx[HUMAN_PARENTS[n]] if n in HUMAN_PARENTS else -1 for n in names])
    off = np.zeros((m, 3))
    for n in names:
        seg, y = segment(n), (-1.0 if n.startswith("l_") else 1.0)
        i = idx[n]
        if n == "abdomen":
            off[i] = np.array([-0.015, 0.0, -0.045]) * H * f["trunk"]
        elif n == "chest":
            off[i] = np.array([0.005, 0.0, -0.11]) * H * f["trunk"]
        elif n == "head":
            off[i] = np.array([0.01, 0.0, -0.17]) * H * f["neck"]
        elif seg == "upper_arm":
            off[i] = np.array([-0.005 * H, y * 0.105 * H * f["shoulder"], -0.135 * H * f["trunk"]])
        elif seg == "forearm":
            off[i] = [0.0, 0.0, 0.186 * H * length("upper_arm", n)]
        elif seg == "hand":
            off[i] = [0.0, 0.0, 0.146 * H * length("forearm", n)]
        elif seg == "thigh":
            off[i] = [0.0, y * 0.051 * H * f["hip"], 0.0]
        elif seg == "shin":
            off[i] = [0.0, 0.0, 0.245 * H * length("thigh", n)]
        elif seg == "foot":
            off[i] = [0.0, 0.0, 0.246 * H * length("shin", n)]

    # Sensor sites on the skin: a point on the bone, pushed out along an outward normal by the limb's
    # radius; the site turns about the bone by a per-subject angle and slides along it a little.
    sens = np.zeros((m, 3))
    normal = np.zeros((m, 3))
    bone_dir = np.tile([0.0, 0.0, 1.0], (m, 1))
    jitter = variation / 0.05
    for n in names:
        i, seg, y = idx[n], segment(n), (-1.0 if n.startswith("l_") else 1.0)
        spin = 0.25 * jitter * rng.normal()
        slide = 0.08 * jitter * rng.normal()
        if n == "pelvis":
            p0, n0 = np.array([-0.11 * s, 0.0, -0.03 * H]), np.array([-1.0, 0.0, 0.0])
        elif n == "abdomen":
            p0, n0 = np.array([-0.10 * s, 0.0, -0.05 * H]), np.array([-1.0, 0.0, 0.0])
        elif n == "chest":
            p0, n0 = np.array([-0.11 * s, 0.0, -0.10 * H]), np.array([-1.0, 0.0, 0.0])
        elif n == "head":
            p0, n0 = np.array([-0.05 * s, 0.0, -0.13 * H * f["neck"]]), np.array([-0.45, 0.0, -0.9])
        elif seg == "foot":
            p0, n0 = np.array([0.06 * s * f["foot"], 0.0, -0.01 * s]), np.array([0.3, 0.0, -1.0])
            bone_dir[i] = [1.0, 0.0, 0.0]
        else:
            frac, radius, n0 = {
                "upper_arm": (0.5, 0.045, np.array([0.0, y, 0.0])),
                "forearm": (0.65, 0.035, np.array([0.3, y, 0.0])),
                "hand": (0.4, 0.015, np.array([0.0, y, 0.0])),
                "thigh": (0.45, 0.075, np.array([0.5, 0.87 * y, 0.0])),
                "shin": (0.35, 0.045, np.array([1.0, 0.0, 0.0])),
            }[seg]
            seg_len = {"upper_arm": 0.186, "forearm": 0.146, "hand": 0.108, "thigh": 0.245, "shin": 0.246}[seg]
            ln = seg_len * H * length(seg, n)
            n0 = rot_z(spin) @ (n0 / np.linalg.norm(n0))
            p0 = np.array([0.0, 0.0, (frac + slide) * ln]) + radius * s * n0
        if n in ("pelvis", "abdomen", "chest", "head") or seg == "foot":
            p0 = p0 + np.array([0.0, 0.02 * s * jitter * rng.normal(), 0.0])
        sens[i] = p0
        normal[i] = n0 / np.linalg.norm(n0)
    # The sensor box lies on the skin: its z axis into the body, x along the bone turned in the skin's
    # plane by a random angle (the strap is never put on quite the same way twice).
    S = np.zeros((m, 3, 3))
    for i in range(m):
        z = -normal[i]
        x = bone_dir[i] - z * (bone_dir[i] @ z)
        x /= np.linalg.norm(x)
        x = axis_angle(z, rng.uniform(-np.pi, np.pi)) @ x
        S[i] = np.column_stack([x, np.cross(z, x), z])

    jt, hinge_axis, limits, rest = [], np.zeros((m, 3)), np.zeros((m, 3, 2)), np.zeros((m, 3))
    for n in names:
        i, seg = idx[n], segment(n)
        if parent[i] < 0:
            jt.append("root")
        elif seg in _HINGE_LIMITS:
            jt.append("hinge")
            tilt = rng.normal(size=3) * 0.03 * jitter + ([0.0, 0.0, 0.0] if seg == "shin" else [0.0, 0.0, 0.08])
            a = np.array([0.0, 1.0, 0.0]) + tilt
            hinge_axis[i] = a / np.linalg.norm(a)
            limits[i, 0] = _HINGE_LIMITS[seg]
            rest[i, 0] = _HINGE_REST[seg]
        else:
            jt.append("ball")
            lim = np.array(_BALL_LIMITS[seg], dtype=float)
            if n.startswith("r_"):
                lim[[0, 2]] = -lim[[0, 2], ::-1]
            limits[i] = lim
            rest[i] = np.clip(0.0, lim[:, 0] + 0.05, lim[:, 1] - 0.05)
            if seg == "thigh":
                rest[i, 1] = 0.05
    # Stand with the back to the transmitter (body forward = +X), pelvis 0.65 m out, the transmitter
    # 0.85 m above the floor: reaching back or forward keeps every sensor in the forward hemisphere
    # (x > 0), and head and feet fit the 36-inch full scale; reaching out and walking need 72 inches.
    hip_h = 0.53 * H
    home_pos = np.array([0.65, 0.0, 0.85 - hip_h])
    model = BodyModel(
        names=names,
        parent=parent,
        joint_offset=off,
        sensor_offset=sens,
        sensor_rotation=S,
        joint_type=tuple(jt),
        hinge_axis=hinge_axis,
        limits=limits,
        rest=rest,
        home_position=home_pos,
        home_rotation=np.eye(3),
        kind="human",
        height=H,
    )
    n_bodies = int(n_bodies)
    if n_bodies == 16:
        return model
    model = _merge_into_parent(model, idx["abdomen"])
    return model.subset(HUMAN_PRIORITY[:n_bodies])


# A wrist or an ankle built as a hinge (`with_hinges`): flexion about the bone frame's y axis, square to
# the forearm and the shin, within about the range a human wrist or ankle bends.
_FLEXION_AXIS = (0.0, 1.0, 0.0)
_FLEXION_LIMITS = (-0.6, 0.5)


def with_hinges(model: BodyModel, segments=("hand", "foot")) -> BodyModel:
    """The same body with the joints of these segments made hinges (a human's "hand": the wrists, "foot":
    the ankles): flexion only, about an axis square to the bone above, resting straight. Takes where a
    hinge sits beside a hinge (docs/design.md §3c), for the solver's tests and benchmarks."""
    wanted = set(segments)
    jt, axis = list(model.joint_type), model.hinge_axis.copy()
    limits, rest = model.limits.copy(), model.rest.copy()
    hit = [i for i, name in enumerate(model.names) if segment(name) in wanted and model.parent[i] >= 0]
    if not hit:
        raise SimulatorError(f"no joint of {', '.join(sorted(wanted))} in this body ({', '.join(model.names)})")
    for i in hit:
        jt[i], axis[i], limits[i], rest[i] = "hinge", _FLEXION_AXIS, 0.0, 0.0
        limits[i, 0] = _FLEXION_LIMITS
    return replace(model, joint_type=tuple(jt), hinge_axis=axis, limits=limits, rest=rest)


def _merge_into_parent(model: BodyModel, k: int) -> BodyModel:
    """Make body k rigid with its parent: its children hang from the parent at the composed rest offset."""
    p = int(model.parent[k])
    off = model.joint_offset.copy()
    lim = model.limits.copy()
    for c in model.children(k):
        off[c] = off[k] + off[c]
        if model.joint_type[c] == "ball" and model.joint_type[k] == "ball":
            lim[c] = lim[c] + lim[k]  # the remaining joint now also does the merged joint's bending
    parent = model.parent.copy()
    parent[parent == k] = p
    full = replace(model, parent=parent, joint_offset=off, limits=lim)
    return full.subset([n for i, n in enumerate(model.names) if i != k])


# ----------------------------------------------------------------------------------------------
# The paper's validation rigs


def linkage(lengths=(0.20, 0.25, 0.30, 0.25, 0.20, 0.15), seed: int = 0) -> BodyModel:
    """A wooden-linkage-like chain: six links joined by five 3-DOF joints with known spacing.

    lengths[k] is link k's length; joint k+1 sits at the far end of link k, so the interior links'
    joint-to-joint distances are lengths[1:5]. Each link carries a sensor on its upper face.
    """
    lengths = np.asarray(lengths, dtype=float)
    if lengths.shape != (6,) or np.any(lengths <= 0.02):
        raise SimulatorError("linkage needs six link lengths, each longer than 2 cm")
    rng = np.random.default_rng([int(seed), 0x11CE])
    m = 6
    names = tuple(f"link{k}" for k in range(m))
    parent = np.arange(m) - 1
    off = np.zeros((m, 3))
    off[1:, 1] = lengths[:-1]  # the chain runs along +Y at rest
    sens = np.column_stack([rng.uniform(-0.01, 0.01, m), lengths * rng.uniform(0.35, 0.65, m), np.full(m, -0.03)])
    S = random_rotations(rng, (m,))
    limits = np.zeros((m, 3, 2))
    limits[1:] = [(-0.9, 0.9), (-0.9, 0.9), (-0.9, 0.9)]
    jt = ("root",) + ("ball",) * (m - 1)
    return BodyModel(
        names=names,
        parent=parent,
        joint_offset=off,
        sensor_offset=sens,
        sensor_rotation=S,
        joint_type=jt,
        hinge_axis=np.zeros((m, 3)),
        limits=limits,
        rest=np.zeros((m, 3)),
        home_position=np.array([0.45, -0.55, 0.15]),
        home_rotation=np.eye(3),
        kind="linkage",
        extra={"link_lengths_m": lengths.tolist()},
    )


def rigid_pair(distance: float = 0.565, seed: int = 0) -> BodyModel:
    """Two sensors rigidly fixed `distance` metres apart (the paper's unit-scale check, §4).

    Body 'sensor_b' hangs from 'sensor_a' by a rigid joint placed at sensor_b's origin, so the truth's
    joint l is sensor_b's origin in sensor_a's frame and its length is the known distance.
    """
    if not 0.01 < distance < 1.5:
        raise SimulatorError(f"rigid pair distance {distance} m is outside 0.01–1.5 m")
    rng = np.random.default_rng([int(seed), 0x9A12])
    S = random_rotations(rng, (2,))
    return BodyModel(
        names=("sensor_a", "sensor_b"),
        parent=np.array([-1, 0]),
        joint_offset=np.array([[0.0, 0.0, 0.0], [0.0, float(distance), 0.0]]),
        sensor_offset=np.zeros((2, 3)),
        sensor_rotation=S,
        joint_type=("root", "rigid"),
        hinge_axis=np.zeros((2, 3)),
        limits=np.zeros((2, 3, 2)),
        rest=np.zeros((2, 3)),
        home_position=np.array([0.55, -0.25, 0.0]),
        home_rotation=np.eye(3),
        kind="rigid_pair",
        extra={"sensor_distance_m": float(distance)},
    )


def by_name(model: str | BodyModel, seed: int = 0, birds: int | None = None, height: float = 1.75) -> BodyModel:
    """Resolve 'human' / 'linkage' / 'pair' (or a BodyModel) to a model with `birds` sensors."""
    if isinstance(model, BodyModel):
        base = model
    elif model == "human":
        return human(height=height, seed=seed, n_bodies=16 if birds is None else birds)
    elif model == "linkage":
        base = linkage(seed=seed)
    elif model in ("pair", "rigid_pair"):
        base = rigid_pair(seed=seed)
    else:
        raise SimulatorError(f"unknown body model {model!r}; choose human, linkage or pair")
    if birds is None or birds == base.m:
        return base
    if not 2 <= birds <= base.m:
        raise SimulatorError(f"the {base.kind} model has {base.m} bodies; --birds must be 2..{base.m}, not {birds}")
    return base.subset(base.names[:birds])
