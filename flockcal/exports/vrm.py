"""VRM 1.0 on the glTF rig: the `VRMC_vrm` extension (each humanoid bone mapped to the rig's node, the
model's meta) and the rest pose VRM asks for, a T-pose facing +Z with Y up, hung from the hips.

The humanoid reading is solver/humanoid.py's (`find_humanoid` on a sample of the take); this module turns
it into the playback the glTF writer plays (exports/gltf.py `gltf_plan`), or says why the tree is no VRM.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from flockcal.exports.bvh import Playback, playback
from flockcal.exports.gltf import Rig, bind_positions, build_rig, joint_notes
from flockcal.solver.humanoid import BONES, Humanoid, find_humanoid, proximal_points, take_sample
from flockcal.solver.reconstruct import Articulation
from flockcal.takes import ChunkedTake

SPEC_VERSION = "1.0"
# VRM 1.0's licence document; its loaders (three-vrm among them) refuse any other URL by default.
LICENSE_URL = "https://vrm.dev/licenses/1.0/"

# VRM 1.0 humanoid.md: the bones a VRM must have, and each bone's parent bone among BONES (chest optional:
# without it, what hangs from the chest hangs from the spine).
REQUIRED = tuple(b for b in BONES if b != "chest")
VRM_PARENT = {
    "spine": "hips", "chest": "spine", "head": "chest",
    "leftUpperArm": "chest", "leftLowerArm": "leftUpperArm", "leftHand": "leftLowerArm",
    "rightUpperArm": "chest", "rightLowerArm": "rightUpperArm", "rightHand": "rightLowerArm",
    "leftUpperLeg": "hips", "leftLowerLeg": "leftUpperLeg", "leftFoot": "leftLowerLeg",
    "rightUpperLeg": "hips", "rightLowerLeg": "rightUpperLeg", "rightFoot": "rightLowerLeg",
}  # fmt: skip


@dataclass(frozen=True, eq=False)
class VrmPlan:
    """A take's VRM: its playback hung from the hips (each body's file axes its T-pose frame, the hips
    pivoting at the start of their bone), each bone's body (articulation index) and the meta; or, for a
    tree that is no humanoid, `reason` and nothing else."""

    reason: str = ""
    playback: Playback | None = None
    bones: dict = field(default_factory=dict)  # VRM bone name → body index in the playback's articulation
    meta: dict = field(default_factory=dict)
    notes: dict = field(default_factory=dict)  # the rig's per-node joint notes, keyed by the body each pivots at

    @property
    def human(self) -> bool:
        return not self.reason

    @property
    def spec(self) -> str | None:
        """The VRMC_vrm version the file carries, None for the plain rig."""
        return SPEC_VERSION if self.human else None

    def rig(self) -> Rig:
        """The glTF rig in the VRM rest: the T-pose, the lowest point of the figure's skeleton (a foot's
        joint or sensor) on y = 0 and the hips above the origin (VRM T-pose §1.3)."""
        pb = self.playback
        rig = build_rig(pb.articulation, pb.A, np.zeros(3), self.notes, pb.names)
        offset = rig.offset.copy()
        offset[0] = [0.0, -bind_positions(rig)[:, 1].min(), 0.0]
        return dataclasses.replace(rig, offset=offset)

    def extension(self, rig: Rig) -> dict:
        """The document's `extensions.VRMC_vrm`: humanBones → the rig's node indices, and the meta."""
        node_of = {b: k for k, b in enumerate(rig.bodies)}
        bones = {bone: {"node": node_of[self.bones[bone]]} for bone in BONES if bone in self.bones}
        return {"specVersion": SPEC_VERSION, "humanoid": {"humanBones": bones}, "meta": self.meta}


def vrm_meta(name: str, authors=("flockcal",)) -> dict:
    """VRM 1.0's required meta (meta.md: name, authors, licenseUrl); every use permission is left at the
    spec's default, the most restrictive, for whoever publishes the avatar to set."""
    authors = [str(a) for a in authors if str(a).strip()] or ["flockcal"]
    return {"name": str(name) or "flockcal", "authors": authors, "licenseUrl": LICENSE_URL}


def plain_rig_note(path, reason: str) -> str:
    """The one line a command prints when the rig it wrote is the plain glTF, not a VRM humanoid."""
    return f"{path}: a plain glTF rig, not a VRM humanoid: {reason}"


def take_humanoid(cal, take: ChunkedTake, *, from_take: bool = False) -> Humanoid:
    """The humanoid of calibration `cal` (a Calibration): the one its fit found (`cal.humanoid`, as `fit --json`
    and the service publish it), else `find_humanoid` on the take's sample (`solver.humanoid.take_sample`),
    as for a calibration read back from its §5 dict, which keeps the bones but not the T-pose frames.
    `from_take`: always found on the take's sample (a live fit's humanoid comes from the frames held live)."""
    hum = getattr(cal, "humanoid", None)
    if hum is not None and hum.posable and not from_take:
        return hum
    f = take_sample(take).frames()
    order = [list(take.names).index(n) for n in cal.names]
    return find_humanoid(cal, f.rotations[:, order], f.positions[:, order], f.valid[:, order])


def vrm_plan(calibration, take: ChunkedTake, up: str = "-z", *, meta: dict | None = None,
             from_take: bool = False) -> VrmPlan:
    """The VRM of `take` played through `calibration` (a Calibration, a KnownFit or a §5 dict; an
    Articulation has no tree data to read a humanoid from), or the reason it has none. `up` is the
    tracker's up axis, as for the BVH: the animation's world; the rest pose is the humanoid's own.
    `from_take`: the humanoid found on `take` itself (`take_humanoid`), whatever the calibration carries."""
    from flockcal.solver.calibration_json import as_calibration
    from flockcal.solver.errors import SolverError

    if isinstance(calibration, Articulation):
        return VrmPlan("an articulation alone carries no fit to find a humanoid in")
    pb = playback(calibration, take, up, "first")  # errors in the calibration or the take come first
    try:
        cal = as_calibration(calibration)
    except SolverError as exc:
        return VrmPlan(f"the calibration cannot be read as a fit ({exc})")
    hum = take_humanoid(cal, take, from_take=from_take)
    if not hum.human:
        return VrmPlan(hum.reason)
    art = pb.articulation
    where = [list(cal.names).index(n) for n in art.names]  # cal's order → the take's (the articulation's)
    bones = [hum.bones[k] for k in where]
    frames = np.asarray(hum.frames, dtype=float)[where]
    body = {b: i for i, b in enumerate(bones) if b is not None}
    if "spine" not in body and "chest" in body:
        # A suit with no abdomen sensor has one trunk body from the lower back up; VRM 1.0 requires the spine
        # (the chest is optional), and that body's bone starts at the lower back, where VRM's spine does.
        body["spine"] = body.pop("chest")
    missing = [b for b in REQUIRED if b not in body]
    if missing:
        return VrmPlan(f"VRM 1.0 needs the bones {', '.join(missing)}, which the humanoid lacks")
    hung = art.rerooted(body["hips"])
    wrong = misplaced(hung, body)
    if wrong:
        return VrmPlan(wrong)
    if not np.isfinite(frames[list(body.values())]).all():
        return VrmPlan("the humanoid has no T-pose frame for some of its bones")
    hum = Humanoid(tuple(bones), hum.world, frames, hum.reason, hum.conflicts)
    c = hung.c.copy()
    c[hung.root] = proximal_points(hung, hum)[hung.root]  # the hips pivot where their bone starts
    hung = dataclasses.replace(hung, c=c)
    pb = Playback(hung, pb.world, rest_axes(hung, frames, pb.first[0]), pb.first, pb.names)
    notes = turned_notes(joint_notes(calibration), art, hung)
    meta = meta if meta is not None else vrm_meta("flockcal")
    return VrmPlan("", pb, {b: int(i) for b, i in body.items()}, meta, notes)


def misplaced(art: Articulation, body: dict[str, int]) -> str:
    """Why the bones do not hang as VRM's humanoid does (each bone's nearest bone above it in the tree must
    be its VRM parent, non-bone bodies allowed between), or "" when they do."""
    bone_of = {i: b for b, i in body.items()}
    for bone, i in body.items():
        want = VRM_PARENT.get(bone)
        while want is not None and want not in body:
            want = VRM_PARENT.get(want)
        above = int(art.parent[i])
        while above >= 0 and above not in bone_of:
            above = int(art.parent[above])
        got = bone_of.get(above)
        if got != want:
            return f"the {bone} hangs from the {got or 'top of the tree'}, where VRM's humanoid has the {want}"
    return ""


def rest_axes(art: Articulation, frames: np.ndarray, first: np.ndarray) -> np.ndarray:
    """(m, 3, 3) each body's file axes A_j: its T-pose frame's transpose for a bone, so that every node's
    rotation is the identity in the T-pose; a body with no bone keeps, at rest, its turn against its
    parent at its first valid frame (`first`: the held first rotations)."""
    A = np.empty((art.n_bodies, 3, 3))
    for j in art.order:
        if np.isfinite(frames[j]).all():
            A[j] = frames[j].T
        else:
            p = art.parent[j]
            A[j] = A[p] @ first[p].T @ first[j] if p >= 0 else np.eye(3)
    return A


def turned_notes(notes: dict[str, dict], old: Articulation, new: Articulation) -> dict[str, dict]:
    """The fit's joint notes (keyed by each joint's child) keyed by the body that pivots at the joint in
    the re-hung tree; a joint that turned round swaps its hinge axes' frames."""
    out = {}
    for i, name in enumerate(old.names):
        note = notes.get(name)
        p = int(old.parent[i])
        if note is None or p < 0:
            continue
        if new.parent[i] == p:
            out[name] = note
        else:  # the joint turned round: the old parent now pivots at it
            out[old.names[p]] = dict(note, axis_child=note.get("axis_parent"), axis_parent=note.get("axis_child"))
    return out
