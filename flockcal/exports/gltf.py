"""glTF 2.0 rig of a calibrated skeleton: joints as nodes, a skin, a plain skinned mesh, and the take
as an animation through the skeleton with the residual removed (three.js, Babylon.js, Blender load it).

Same skeleton and rotations as the BVH export (exports/bvh.py): one node per body pivoting at its
inboard joint, the BVH's names, offsets and rest pose; metres and Y-up. `.glb` (binary) or `.gltf`
(JSON with the buffer embedded) by the file's extension. Written with numpy, json and struct only.
The take is played a chunk of frames at a time into the buffer's blocks: in memory for a file
(`gltf_bytes`), through a temporary file for the service's streamed download (`glb_chunks`).
"""

from __future__ import annotations

import base64
import json
import os
import struct
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from flockcal.atomic import write_pieces
from flockcal.errors import FlockcalError
from flockcal.exports.bvh import Playback, bvh_names, depth_first, local_rotations, playback, rest_pose
from flockcal.rotations import as_quat
from flockcal.solver.reconstruct import Articulation, Reconstruction, reconstruct
from flockcal.takes import ChunkedTake

GLB_MAGIC, GLB_JSON, GLB_BIN = 0x46546C67, 0x4E4F534A, 0x004E4942
FLOAT, UBYTE, USHORT, UINT = 5126, 5121, 5123, 5125
ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963

# The figure any viewer shows: thin enough that a hand's bones stay apart, thick enough to see at 3 m.
BONE_RADIUS_M = 0.015
JOINT_RADIUS_M = 0.025


class GltfError(FlockcalError, ValueError):
    """A glTF output that cannot be written as asked (an unknown file extension)."""


def binary_for(path: str | os.PathLike, option: str = "") -> bool:
    """True for a .glb path, False for .gltf; GltfError (naming `option`, e.g. "--gltf") for anything else."""
    suffix = Path(path).suffix.lower()
    if suffix not in (".glb", ".gltf"):
        where = f"{option} {path}" if option else str(path)
        raise GltfError(f"{where}: a glTF file ends in .glb (binary) or .gltf (JSON); rename it")
    return suffix == ".glb"


@dataclass(frozen=True)
class Rig:
    """The node tree of the file: bodies in depth-first order, then one end node per leaf (its sensor)."""

    art: Articulation
    bodies: list[int]  # articulation index of node k, for k < len(bodies)
    names: list[str]  # every node's name (bodies, then ends)
    parent: np.ndarray  # (nodes,) node index of the parent, -1 at the root
    offset: np.ndarray  # (nodes, 3) translation in the parent node's axes (metres); the root's is its rest position
    extras: list[dict]  # per node: what kind of joint it pivots at (and a hinge's axis in its own axes)


def joint_notes(calibration) -> dict[str, dict]:
    """{child sensor name: its §5 joint entry} when the calibration carries them (not for an Articulation)."""
    if isinstance(calibration, Articulation):
        return {}
    data = calibration if isinstance(calibration, dict) else calibration.to_dict()
    return {str(j["child"]): j for j in data.get("joints", []) if isinstance(j, dict) and "child" in j}


def build_rig(art: Articulation, A: np.ndarray, root_rest: np.ndarray, notes: dict[str, dict],
              names: list[str] | None = None) -> Rig:
    """The rig of a completed articulation with file axes A (rest_frames) and the root's rest position;
    `names`: each body's node name (`bvh.node_names`: humanoid bones on a human tree; default its sensor's)."""
    bodies = depth_first(art)
    node_of = {b: k for k, b in enumerate(bodies)}
    origin = art.origin()
    leaves = [b for b in bodies if not art.children(b)]
    base = list(names) if names is not None else list(art.names)
    safe = bvh_names(base + [f"{base[b]}_end" for b in leaves])
    names = [safe[b] for b in bodies] + safe[art.n_bodies:]
    parent = [-1 if art.parent[b] < 0 else node_of[int(art.parent[b])] for b in bodies]
    offset = [root_rest if b == art.root else A[art.parent[b]] @ (art.l[b] - origin[art.parent[b]]) for b in bodies]
    extras = []
    for b in bodies:
        name = art.names[b]
        note = notes.get(name, {})
        if b == art.root:
            kind = "root"
        elif art.rigid is not None and art.rigid[b]:
            kind = "rigid"
        elif note.get("hinge"):
            kind = "hinge"
        elif note.get("determined") is False:
            kind = "undetermined"
        else:
            kind = "ball"
        extra = {"sensor": name, "joint": kind}
        if kind == "hinge" and note.get("axis_child") is not None:
            extra["hinge_axis"] = [round(float(x), 9) for x in A[b] @ np.asarray(note["axis_child"], dtype=float)]
        extras.append({"flockcal": extra})
    for b in leaves:  # a leaf ends at its sensor, as the BVH's End Site
        parent.append(node_of[b])
        offset.append(A[b] @ -origin[b])
        extras.append({"flockcal": {"sensor": art.names[b], "end_site": True}})
    return Rig(art, bodies, names, np.asarray(parent), np.asarray(offset, dtype=float), extras)


def bind_positions(rig: Rig) -> np.ndarray:
    """(nodes, 3) node origins in the bind pose: every node rotation identity (the rest pose)."""
    pos = np.zeros_like(rig.offset)
    for k, p in enumerate(rig.parent):  # parents come before children in node order
        pos[k] = rig.offset[k] + (pos[p] if p >= 0 else 0.0)
    return pos


# --- the plain figure ----------------------------------------------------------------------------
def _capsule(a: np.ndarray, b: np.ndarray, radius: float, seg: int = 12, rings: int = 4):
    """(vertices, normals, triangles) of a capsule from a to b (a sphere when a == b), outward winding."""
    d = b - a
    length = float(np.linalg.norm(d))
    z = d / length if length > 1e-9 else np.array([0.0, 0.0, 1.0])
    x = np.cross(z, [1.0, 0, 0] if abs(z[0]) < 0.9 else [0, 1.0, 0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    if length > 1e-9:  # two hemispheres, their equators joined by the cylinder
        theta = np.concatenate([np.linspace(-np.pi / 2, 0, rings + 1)[1:], np.linspace(0, np.pi / 2, rings + 1)[:-1]])
        lift = np.r_[np.zeros(rings), np.full(rings, length)]
    else:  # a sphere: one equator, else its band would be zero-area triangles
        theta = np.linspace(-np.pi / 2, np.pi / 2, 2 * rings + 1)[1:-1]
        lift = np.zeros(len(theta))
    phi = np.linspace(0, 2 * np.pi, seg, endpoint=False)
    n_local = np.stack([np.cos(theta)[:, None] * np.cos(phi), np.cos(theta)[:, None] * np.sin(phi),
                        np.broadcast_to(np.sin(theta)[:, None], (len(theta), seg))], axis=-1).reshape(-1, 3)
    p_local = radius * n_local + np.repeat(lift, seg)[:, None] * [0, 0, 1.0]
    n_local = np.vstack([n_local, [[0, 0, -1.0], [0, 0, 1.0]]])
    p_local = np.vstack([p_local, [[0, 0, -radius], [0, 0, length + radius]]])
    basis = np.stack([x, y, z])  # local → model: v @ basis
    rows = len(theta)
    k = np.arange(seg)
    k1 = (k + 1) % seg
    tris = []
    for r in range(rows - 1):
        i0, i1 = r * seg, (r + 1) * seg
        tris += [np.stack([i0 + k, i0 + k1, i1 + k1], 1), np.stack([i0 + k, i1 + k1, i1 + k], 1)]
    bottom, top = rows * seg, rows * seg + 1
    tris.append(np.stack([np.full(seg, bottom), k1, k], 1))
    tris.append(np.stack([np.full(seg, top), (rows - 1) * seg + k, (rows - 1) * seg + k1], 1))
    return p_local @ basis + a, n_local @ basis, np.vstack(tris)


def figure(rig: Rig, pos: np.ndarray):
    """(positions, normals, joints, triangles): a sphere at each body's pivot and a capsule along each
    bone (pivot to child pivot or to a leaf's sensor), every vertex bound to the node it moves with."""
    parts = []
    for k in range(len(rig.bodies)):
        parts.append((_capsule(pos[k], pos[k], JOINT_RADIUS_M), k))
    for k, p in enumerate(rig.parent):
        if p >= 0 and np.linalg.norm(pos[k] - pos[p]) > 1e-6:
            parts.append((_capsule(pos[p], pos[k], BONE_RADIUS_M), p))
    verts, normals, joints, tris, base = [], [], [], [], 0
    for (v, n, t), node in parts:
        verts.append(v)
        normals.append(n)
        joints.append(np.full(len(v), node))
        tris.append(t + base)
        base += len(v)
    return np.vstack(verts), np.vstack(normals), np.concatenate(joints), np.vstack(tris)


# --- the animation ---------------------------------------------------------------------------------
def animation_rows(rec: Reconstruction, world: np.ndarray, A: np.ndarray, rig: Rig, previous=None):
    """(quaternions (n, bodies, 4) xyzw float32 in node order, root translation (n, 3) float32 metres).

    The BVH's local rotations (exports/bvh.local_rotations). Each quaternion takes the sign nearest the
    frame before it (`previous`: the last row of an earlier chunk), so interpolation never spins the long way.
    """
    local = local_rotations(rec, world, A)[:, rig.bodies]
    q = as_quat(local, scalar_first=False)
    prev = q[:1] if previous is None else np.asarray(previous, dtype=float)[None]
    dots = np.einsum("nmk,nmk->nm", q, np.concatenate([prev, q[:-1]]))
    q *= np.cumprod(np.where(dots < 0, -1.0, 1.0), axis=0)[..., None]
    root = rec.joint_positions[:, rec.articulation.root] @ world.T
    return q.astype(np.float32), root.astype(np.float32)


def key_times(times: np.ndarray, rate_hz: float) -> np.ndarray:
    """Keyframe times in seconds from the first frame: the take's own clock when it strictly increases
    (glTF requires that), else frame / rate as the BVH's Frame Time."""
    t = np.asarray(times, dtype=float) - (times[0] if len(times) else 0.0)
    t32 = t.astype(np.float32)
    if len(t32) > 1 and not (np.diff(t32) > 0).all():
        t32 = (np.arange(len(t)) / rate_hz).astype(np.float32)
    return t32


# --- the file ----------------------------------------------------------------------------------------
class _Buffer:
    """The binary buffer being laid out: views aligned to 4 bytes, accessors over them. A part is bytes,
    or an int: that many bytes the animation fills in later (so a long take can be written in chunks)."""

    def __init__(self):
        self.parts: list[bytes | int] = []
        self.size = 0
        self.views: list[dict] = []
        self.accessors: list[dict] = []

    def add(self, array: np.ndarray | None, component: int, kind: str, target: int | None = None,
            bounds: bool = False, count: int = 0) -> int:
        """An accessor over `array`, or with array=None over `count` elements reserved for later."""
        width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4, "MAT4": 16}[kind]
        data = np.ascontiguousarray(array).tobytes() if array is not None else 4 * width * count
        size = len(data) if array is not None else data
        view = {"buffer": 0, "byteOffset": self.size, "byteLength": size}
        if target is not None:
            view["target"] = target
        self.parts.append(data)
        pad = -size % 4
        if pad:
            self.parts.append(b"\0" * pad)
        self.size += size + pad
        self.views.append(view)
        acc = {"bufferView": len(self.views) - 1, "componentType": component,
               "count": int(len(array)) if array is not None else int(count), "type": kind}
        if bounds:
            flat = np.asarray(array, dtype=float).reshape(len(array), -1)
            acc["min"] = flat.min(axis=0).tolist()
            acc["max"] = flat.max(axis=0).tolist()
        self.accessors.append(acc)
        return len(self.accessors) - 1

    def offset_of(self, accessor: int) -> int:
        return self.views[self.accessors[accessor]["bufferView"]]["byteOffset"]


@dataclass(frozen=True)
class Layout:
    """The file but for its animation values: the JSON, the buffer's parts (bytes, or an int for a
    reserved block), and where the root's translations and each body's rotations go in the buffer."""

    doc: dict
    parts: list
    size: int
    root_at: int  # byte offset of the (n, 3) float32 root translations (-1: no animation)
    rotation_at: list[int]  # byte offset of body node k's (n, 4) float32 quaternions


def gltf_plan(calibration, take: ChunkedTake, *, up: str = "-z", rest: str | int = "tpose", name: str = "take",
              animation: bool = True, vrm=None) -> tuple[Layout, Playback, Rig]:
    """The file of `take` played through `calibration` (a Calibration, a KnownFit, a §5 dict or an
    Articulation), as `bvh_chunks` plays it, but for its animation values (`fill_animation`); animation=False:
    the rig alone (no pass over the frames but the first valid pose and any rigid sensor's mean).

    rest="tpose" (the default): a VRM 1.0 humanoid in its T-pose when the tree is human-shaped
    (`exports.vrm.vrm_plan`, or `vrm`: that plan made beforehand), else the rest of "first" with the
    reason in the file's extras; "first", a frame index or "sensor": the plain rig (see bvh.rest_frames)."""
    plan_vrm, plain = None, rest
    if rest == "tpose":
        from flockcal.exports.vrm import vrm_meta, vrm_plan

        plan_vrm, plain = (vrm if vrm is not None else vrm_plan(calibration, take, up, meta=vrm_meta(name))), "first"
    if plan_vrm is not None and plan_vrm.human:
        pb, rig = plan_vrm.playback, plan_vrm.rig()
    else:
        pb = playback(calibration, take, up, plain)
        art = pb.articulation
        R, t = rest_pose(take, plain, pb.first)
        root = reconstruct(R[None], t[None], art).joint_positions[0, art.root]  # the root joint at the rest frame
        rig = build_rig(art, pb.A, pb.world @ root, joint_notes(calibration), pb.names)
    times = np.concatenate([f.times for f in take.chunks()]) if animation else None  # 8 bytes a frame
    extras = file_extras(up, rest, take.rate_hz)
    if plan_vrm is not None:
        extras["vrm"] = plan_vrm.spec
        if not plan_vrm.human:
            extras["rest"], extras["vrm_reason"] = "first", plan_vrm.reason
    plan = layout(rig, None if times is None else key_times(times, take.rate_hz), name=name, extras=extras)
    if plan_vrm is not None and plan_vrm.human:  # VRM 1.0: the humanoid's bones on the rig's nodes
        plan.doc["extensionsUsed"] = ["VRMC_vrm"]
        plan.doc["extensions"] = {"VRMC_vrm": plan_vrm.extension(rig)}
    return plan, pb, rig


def fill_animation(plan: Layout, pb: Playback, rig: Rig, take: ChunkedTake, write: Callable[[int, bytes], None],
                   chunk_frames: int | None = None) -> None:
    """Play `take` a chunk at a time and `write(offset, data)` each chunk's rows into the buffer's
    reserved blocks (glTF keeps each joint's keyframes in one block, so a chunk's rows land in every block)."""
    k, last = 0, None
    for rec in pb.chunks(take, chunk_frames):
        if not len(rec.rotations):
            continue
        quats, root = animation_rows(rec, pb.world, pb.A, rig, previous=last)
        last = quats[-1]
        for at, rows, width in [(plan.root_at, root, 12)] + [
                (plan.rotation_at[j], quats[:, j], 16) for j in range(quats.shape[1])]:
            write(at + k * width, np.ascontiguousarray(rows, dtype=np.float32).tobytes())
        k += len(quats)


def gltf_document(calibration, take: ChunkedTake, *, up: str = "-z", rest: str | int = "tpose", name: str = "take",
                  chunk_frames: int | None = None, vrm=None):
    """(the glTF JSON as a dict, the binary buffer) for `take` played through `calibration`, in memory."""
    plan, pb, rig = gltf_plan(calibration, take, up=up, rest=rest, name=name, vrm=vrm)
    out = bytearray(b"".join(p if isinstance(p, bytes) else bytes(p) for p in plan.parts))

    def write(at: int, data: bytes) -> None:
        out[at:at + len(data)] = data

    fill_animation(plan, pb, rig, take, write, chunk_frames)
    return plan.doc, bytes(out)


def glb_chunks(calibration, take: ChunkedTake, *, up: str = "-z", rest: str | int = "tpose", name: str = "take",
               animation: bool = True, chunk_frames: int | None = None, out_bytes: int = 256 * 1024,
               vrm=None) -> Iterator[bytes]:
    """The .glb of `gltf_bytes` as pieces for a download whose memory must not grow with the take (the
    service's frame log): the head first, then the buffer, its animation blocks filled chunk by chunk in a
    temporary file and sent `out_bytes` at a time. Errors in the calibration or the take are raised by the
    first next(), before any byte. animation=False: the rig alone (193 kB for 16 bodies)."""
    plan, pb, rig = gltf_plan(calibration, take, up=up, rest=rest, name=name, animation=animation, vrm=vrm)
    if not animation:
        yield glb_head(plan.doc, plan.size) + b"".join(plan.parts)
        return
    yield glb_head(plan.doc, plan.size)
    yield from buffer_pieces(plan, pb, rig, take, chunk_frames, out_bytes)


def buffer_pieces(plan: Layout, pb: Playback, rig: Rig, take: ChunkedTake, chunk_frames: int | None = None,
                  out_bytes: int = 256 * 1024) -> Iterator[bytes]:
    """The binary buffer of `plan`, its animation blocks filled chunk by chunk in a temporary file, read
    back `out_bytes` at a time: memory holds a chunk of the take and a piece, whatever its length."""
    with tempfile.TemporaryFile() as buf:
        for part in plan.parts:
            if isinstance(part, bytes):
                buf.write(part)
            else:
                buf.seek(part, os.SEEK_CUR)  # a reserved block: filled below
        buf.truncate(plan.size)

        def write(at: int, data: bytes) -> None:
            buf.seek(at)
            buf.write(data)

        fill_animation(plan, pb, rig, take, write, chunk_frames)
        buf.seek(0)
        while piece := buf.read(out_bytes):
            yield piece


DATA_URI = "data:application/octet-stream;base64,"
_BUFFER_MARK = "@flockcal-buffer@"  # where the base64 goes in the JSON text (no JSON escaping touches it)


def gltf_json_chunks(calibration, take: ChunkedTake, *, up: str = "-z", rest: str | int = "tpose", name: str = "take",
                     chunk_frames: int | None = None, vrm=None) -> Iterator[bytes]:
    """The .gltf form of `gltf_bytes` (one JSON file, its buffer a base64 data URI) as pieces: the text
    before the buffer, the buffer encoded a piece at a time, the text after it."""
    plan, pb, rig = gltf_plan(calibration, take, up=up, rest=rest, name=name, vrm=vrm)
    doc = dict(plan.doc, buffers=[{"byteLength": plan.size, "uri": DATA_URI + _BUFFER_MARK}])
    head, tail = json.dumps(doc, separators=(",", ":")).split(_BUFFER_MARK)
    yield head.encode("utf-8")
    left = b""
    for piece in buffer_pieces(plan, pb, rig, take, chunk_frames):
        data = left + piece
        cut = len(data) - len(data) % 3  # whole 3-byte groups: the pieces' base64 joins into the whole's
        yield base64.b64encode(data[:cut])
        left = data[cut:]
    yield base64.b64encode(left) + tail.encode("utf-8")


def file_extras(up: str, rest, rate_hz: float) -> dict:
    """What the file says about itself under extras.flockcal."""
    return {"units": "m", "up": "+y", "tracker_up": up, "rest": rest, "rate_hz": float(rate_hz)}


def layout(rig: Rig, times: np.ndarray | None, name: str = "take", extras: dict | None = None) -> Layout:
    """The document of a rig and its keyframe times (key_times), its animation values still to fill;
    times None: the rig alone, no animation (what a page loads to drive from the live pose's `rig`)."""
    pos = bind_positions(rig)
    buf = _Buffer()
    verts, normals, vjoints, tris = figure(rig, pos)
    a_pos = buf.add(verts.astype(np.float32), FLOAT, "VEC3", ARRAY_BUFFER, bounds=True)
    a_nrm = buf.add(normals.astype(np.float32), FLOAT, "VEC3", ARRAY_BUFFER)
    joints4 = np.zeros((len(vjoints), 4), dtype=np.uint8 if len(rig.names) < 256 else np.uint16)
    joints4[:, 0] = vjoints
    a_jnt = buf.add(joints4, UBYTE if joints4.dtype == np.uint8 else USHORT, "VEC4", ARRAY_BUFFER)
    weights = np.zeros((len(vjoints), 4), dtype=np.float32)
    weights[:, 0] = 1.0
    a_wgt = buf.add(weights, FLOAT, "VEC4", ARRAY_BUFFER)
    index_type = np.uint16 if len(verts) < 65535 else np.uint32
    a_idx = buf.add(tris.reshape(-1).astype(index_type), USHORT if index_type is np.uint16 else UINT, "SCALAR",
                    ELEMENT_ARRAY_BUFFER)
    # Inverse bind matrices: the inverse of each joint's global transform in the bind (rest) pose, column-major.
    bind = np.tile(np.eye(4), (len(pos), 1, 1))
    bind[:, :3, 3] = pos
    ibm = np.linalg.inv(bind)
    a_ibm = buf.add(np.swapaxes(ibm, 1, 2).reshape(len(pos), 16).astype(np.float32), FLOAT, "MAT4")
    samplers, channels, a_root, a_rot = [], [], None, []
    if times is not None:
        n = len(times)
        a_time = buf.add(np.asarray(times, dtype=np.float32), FLOAT, "SCALAR", bounds=True)
        a_root = buf.add(None, FLOAT, "VEC3", count=n)
        samplers.append({"input": a_time, "output": a_root, "interpolation": "LINEAR"})
        channels.append({"sampler": 0, "target": {"node": 0, "path": "translation"}})
        for k in range(len(rig.bodies)):
            a_rot.append(buf.add(None, FLOAT, "VEC4", count=n))
            samplers.append({"input": a_time, "output": a_rot[-1], "interpolation": "LINEAR"})
            channels.append({"sampler": len(samplers) - 1, "target": {"node": k, "path": "rotation"}})

    nodes = []
    for k, nm in enumerate(rig.names):
        node = {"name": nm, "translation": [float(x) for x in rig.offset[k]], "extras": rig.extras[k]}
        kids = [int(c) for c in np.flatnonzero(rig.parent == k)]
        if kids:
            node["children"] = kids
        nodes.append(node)
    mesh_node = len(nodes)
    nodes.append({"name": "figure", "mesh": 0, "skin": 0})
    doc = {
        "asset": {"version": "2.0", "generator": "flockcal (flockcal/exports/gltf.py)"},
        "scene": 0,
        "scenes": [{"name": name, "nodes": [0, mesh_node]}],
        "nodes": nodes,
        "meshes": [{"name": "figure", "primitives": [{
            "attributes": {"POSITION": a_pos, "NORMAL": a_nrm, "JOINTS_0": a_jnt, "WEIGHTS_0": a_wgt},
            "indices": a_idx, "material": 0, "mode": 4}]}],
        "materials": [{"name": "figure", "pbrMetallicRoughness": {"baseColorFactor": [0.75, 0.75, 0.78, 1.0],
                                                                   "metallicFactor": 0.0, "roughnessFactor": 0.8}}],
        "skins": [{"name": "skeleton", "inverseBindMatrices": a_ibm, "joints": list(range(len(rig.names))),
                   "skeleton": 0}],
        "animations": [{"name": name, "samplers": samplers, "channels": channels}],
        "accessors": buf.accessors,
        "bufferViews": buf.views,
        "buffers": [{"byteLength": buf.size}],
    }
    if times is None:
        del doc["animations"]
    if extras:
        doc["extras"] = {"flockcal": extras}
    return Layout(doc, buf.parts, buf.size, buf.offset_of(a_root) if a_root is not None else -1,
                  [buf.offset_of(a) for a in a_rot])


def glb_head(doc: dict, bin_size: int) -> bytes:
    """The binary glTF container up to its buffer: 12-byte header, the JSON chunk (space-padded), the BIN
    chunk's header. `bin_size` must be a multiple of 4 (layouts are)."""
    text = json.dumps(doc, separators=(",", ":")).encode("utf-8")
    text += b" " * (-len(text) % 4)
    total = 12 + 8 + len(text) + 8 + bin_size
    return b"".join([struct.pack("<III", GLB_MAGIC, 2, total), struct.pack("<II", len(text), GLB_JSON), text,
                     struct.pack("<II", bin_size, GLB_BIN)])


def glb(doc: dict, binary: bytes) -> bytes:
    """The .glb file: glb_head, then the buffer (zero-padded to 4 bytes)."""
    binary += b"\0" * (-len(binary) % 4)
    return glb_head(doc, len(binary)) + binary


def gltf_json(doc: dict, binary: bytes) -> bytes:
    """The .gltf form: one JSON file, its buffer embedded as a base64 data URI."""
    doc = dict(doc, buffers=[{"byteLength": len(binary),
                              "uri": DATA_URI + base64.b64encode(binary).decode("ascii")}])
    return json.dumps(doc, separators=(",", ":")).encode("utf-8")


def gltf_bytes(calibration, take, *, binary: bool = True, **options) -> bytes:
    """The whole file in memory: .glb bytes (binary=True) or .gltf JSON text."""
    doc, data = gltf_document(calibration, take, **options)
    return glb(doc, data) if binary else gltf_json(doc, data)


def write_gltf(path: str | os.PathLike, calibration, take, **options) -> str:
    """Write the rig to `path`, .glb or .gltf by its extension, the take a chunk at a time (atomically:
    never a half-written file). Returns "" when the file is a VRM 1.0 humanoid or was not asked to be one
    (rest other than "tpose"), else why the tree is no humanoid (the file is then the plain rig)."""
    binary = binary_for(path)
    options.setdefault("name", Path(path).stem)
    if options.get("rest", "tpose") == "tpose" and options.get("vrm") is None:
        from flockcal.exports.vrm import vrm_meta, vrm_plan

        options["vrm"] = vrm_plan(calibration, take, options.get("up", "-z"), meta=vrm_meta(options["name"]))
    write_pieces(path, (glb_chunks if binary else gltf_json_chunks)(calibration, take, **options))
    vrm = options.get("vrm")
    return vrm.reason if vrm is not None else ""
