"""Which humanoid bone each body is (VRM 1.0 names), found from the fitted tree and the take's geometry.

INTERFACE STUB (session 48): the signatures and conventions below are what the exports (VRM, TRC) and the
live streams (VRPN, VMC) are written against. The body of `find_humanoid` is a placeholder that reads the
simulator's sensor names; it is replaced by the finding from the tree and the data.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# VRM 1.0 `humanoid.humanBones` names, in the order of the VRPN sensors (sensor k is BONES[k]).
BONES: tuple[str, ...] = (
    "hips", "spine", "chest", "head",
    "leftUpperArm", "leftLowerArm", "leftHand", "rightUpperArm", "rightLowerArm", "rightHand",
    "leftUpperLeg", "leftLowerLeg", "leftFoot", "rightUpperLeg", "rightLowerLeg", "rightFoot",
)


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
    """

    bones: tuple
    world: np.ndarray
    frames: np.ndarray
    reason: str = ""
    conflicts: tuple = field(default_factory=tuple)  # NameConflict, …

    @property
    def human(self) -> bool:
        return not self.reason

    def sensor(self, bone: str) -> int | None:
        """The sensor index of `bone`, or None when no body is that bone."""
        try:
            return self.bones.index(bone)
        except ValueError:
            return None

    def mapping(self, names) -> dict[str, str]:
        """{sensor name: bone} for every body with a bone."""
        return {str(names[i]): b for i, b in enumerate(self.bones) if b is not None}


_STUB_NAMES = {
    "pelvis": "hips", "abdomen": "spine", "chest": "chest", "head": "head",
    "l_upper_arm": "leftUpperArm", "l_forearm": "leftLowerArm", "l_hand": "leftHand",
    "r_upper_arm": "rightUpperArm", "r_forearm": "rightLowerArm", "r_hand": "rightHand",
    "l_thigh": "leftUpperLeg", "l_shin": "leftLowerLeg", "l_foot": "leftFoot",
    "r_thigh": "rightUpperLeg", "r_shin": "rightLowerLeg", "r_foot": "rightFoot",
}


def find_humanoid(cal, rotations: np.ndarray, positions: np.ndarray, valid: np.ndarray | None = None) -> Humanoid:
    """The humanoid bone of every body of `cal`, from its tree and a sample of the take's frames
    (`rotations` (n, m, 3, 3), `positions` (n, m, 3), `valid` (n, m)). STUB: reads simulator names."""
    m = len(cal.names)
    bones = tuple(_STUB_NAMES.get(str(n)) for n in cal.names)
    reason = "" if all(b is not None for b in bones) else "stub: sensor names are not the simulator's"
    if reason:
        bones = (None,) * m
    # The Flock's world is +Z down; the stub takes that as up = -Z and heading +X.
    world = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
    frames = np.repeat(np.eye(3)[None], m, axis=0)
    return Humanoid(bones, world, frames, reason)


def proximal_points(cal, hum: Humanoid) -> np.ndarray:
    """(m, 3) where each body's bone starts, in its own sensor frame: its inboard joint's centre (`c`), and
    for the root the midpoint of its two hip joints when both upper legs hang from it (the hips' centre on a
    human tree rooted at the hips), else the mean of its outboard joints' centres (`l`)."""
    m = len(cal.names)
    pts = np.full((m, 3), np.nan)
    pairs, c, l = cal.joint_arrays()
    pts[pairs[:, 0]] = c
    at_root = pairs[:, 1] == cal.root
    # The spine's joint hangs from the hips too: the mean of all three sat a third of the way up the back.
    legs = at_root & np.isin(pairs[:, 0], [i for i in (hum.sensor("leftUpperLeg"), hum.sensor("rightUpperLeg"))
                                           if i is not None])
    use = legs if legs.sum() == 2 else at_root
    if use.any():
        pts[cal.root] = l[use].mean(axis=0)
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
