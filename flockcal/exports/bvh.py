"""BVH export of a take played back through its calibration (Blender, MotionBuilder, Maya import it).

Each body pivots at its inboard joint (the root at its sensor, with the position channels); its BVH
axes are its sensor axes turned so the rest pose is the take's first frame. Joints are named by their
humanoid bone on a human tree (ROOT Hips), else by sensor. Centimetres and Y-up in
the file, SI everywhere else. The take is read a chunk of frames at a time (`bvh_chunks`), so the CLI's
file and the service's streamed download of a session of any length come from the same writer.
"""

from __future__ import annotations

import io
import os
import re
import warnings
from dataclasses import dataclass
from typing import Iterator

import numpy as np
from scipy.spatial.transform import Rotation

from flockcal.atomic import write_pieces
from flockcal.errors import FlockcalError
from flockcal.solver.reconstruct import (Articulation, Reconstruction, articulation, first_valid, held_poses,
                                         reconstruct_chunks)
from flockcal.takes import ChunkedTake

class BvhError(FlockcalError, ValueError):
    """An export option that makes no sense (unknown units, up axis or rest frame)."""


UNITS_PER_METRE = {"cm": 100.0, "m": 1.0, "mm": 1000.0, "in": 100.0 / 2.54}

# Rotation channels are written Z, X, Y: BVH composes them in the listed order (R = Rz·Rx·Ry, intrinsic),
# which scipy calls the "ZXY" sequence, so decomposition and recomposition are exact.
ROTATION_CHANNELS = ("Zrotation", "Xrotation", "Yrotation")
_EULER_SEQ = "ZXY"

# Rotations taking the tracker's world frame to BVH's Y-up frame, keyed by the tracker's up axis.
UP_AXES = {
    "+y": np.eye(3),
    "+z": np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]]),  # Z-up (many optical labs)
    "-z": np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]]),  # Z-down: the Flock's transmitter frame, the simulator's
}


def bvh_world(up: str) -> np.ndarray:
    """3×3 rotation from the tracker world frame (whose up axis is `up`) to the BVH file's frame."""
    try:
        return UP_AXES[up]
    except KeyError:
        raise BvhError(f"up must be one of {', '.join(UP_AXES)}, got {up!r}") from None


def bvh_names(names) -> list[str]:
    """Sensor names made safe for BVH (no whitespace or braces), still unique."""
    out: list[str] = []
    for name in names:
        safe = re.sub(r"[^A-Za-z0-9_.:-]", "_", str(name)) or "body"
        base, k = safe, 1
        while safe in out:
            k += 1
            safe = f"{base}_{k}"
        out.append(safe)
    return out


def node_names(calibration, names) -> list[str]:
    """BVH joint and glTF node names for the bodies `names` (sensor names, in the order wanted): on a human
    tree each body's humanoid bone in PascalCase ("Hips", "LeftUpperArm", docs/outputs.md), else its sensor
    name made BVH-safe (`bvh_names`); unique either way. `calibration`: a Calibration, its §5 dict, an
    Articulation (sensor names: it carries no humanoid)."""
    from flockcal.solver.humanoid import node_name

    bones = humanoid_bones(calibration)
    wanted = [node_name(bones[str(x)]) if str(x) in bones else str(x) for x in names]
    return bvh_names(wanted)


def humanoid_bones(calibration) -> dict[str, str]:
    """{sensor name: humanoid bone} of a human tree's calibration (a Calibration or its §5 dict), else {}."""
    if isinstance(calibration, dict):
        mapping = calibration.get("humanoid")
        return {str(k): str(v) for k, v in mapping.items()} if isinstance(mapping, dict) else {}
    hum = getattr(calibration, "humanoid", None)
    return hum.mapping(calibration.names) if hum is not None and hum.human else {}


def _euler_degrees(R: np.ndarray) -> np.ndarray:
    """(…, 3) angles in degrees in channel order Z, X, Y for rotation matrices (…, 3, 3)."""
    shape = R.shape[:-2]
    with warnings.catch_warnings():
        # At gimbal lock scipy still returns angles that recompose to the same matrix; only the split
        # between the first and third angle is arbitrary, which BVH consumers accept.
        warnings.simplefilter("ignore", UserWarning)
        angles = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_euler(_EULER_SEQ, degrees=True)
    return angles.reshape(*shape, 3)


def depth_first(art: Articulation) -> list[int]:
    """Bodies in the order the HIERARCHY lists them (depth first), which is the MOTION column order."""
    out: list[int] = []
    stack = [art.root]
    while stack:
        i = stack.pop()
        out.append(i)
        stack.extend(reversed(art.children(i)))
    return out


def rest_frames(take: ChunkedTake, world: np.ndarray, rest: str | int,
                first: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """(m, 3, 3) A_j: each body's BVH frame in its sensor frame's terms, so BVH frame = R_j A_jᵀ.

    rest="sensor": A = I, every BVH frame is its sensor frame (the rest pose is all sensors aligned,
    which looks tangled). rest="first" (or a frame index): A_j = W R_j(k0), so the file's rest pose is
    the performer's pose at that frame, upright in the Y-up file, which is what animators expect.
    `first`: each sensor's first valid pose (`first_valid`: what a take holds before a sensor's first record).
    """
    if rest == "sensor":
        return np.broadcast_to(np.eye(3), first[0].shape).copy()
    return world @ rest_pose(take, rest, first)[0]  # held rotations: defined at every frame


def rest_pose(take: ChunkedTake, rest: str | int,
              first: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """((m, 3, 3), (m, 3)): the held pose at the rest frame (0 for "first" and "sensor", else the frame
    index `rest`), read up to that frame a chunk at a time; `first` = `first_valid` of the take."""
    if isinstance(rest, str) and rest in ("first", "sensor"):
        return first
    n = take.n_frames
    if not (isinstance(rest, (int, np.integer)) and 0 <= int(rest) < n):
        raise BvhError(f"rest must be 'first', 'sensor' or a frame index in 0..{n - 1}, got {rest!r}")
    k, held = int(rest), first
    for f in take.chunks():
        R, t = held_poses(f.rotations, f.positions, f.valid, before=held)
        if k < len(R):
            return R[k], t[k]
        k -= len(R)
        held = (R[-1], t[-1])
    raise BvhError(f"the take ended before its frame {rest}")  # n_frames said otherwise


def local_rotations(rec: Reconstruction, world: np.ndarray, A: np.ndarray) -> np.ndarray:
    """(n, m, 3, 3) each body's rotation in its parent's file axes, indexed like the articulation.

    Child j under p: A_p R_pᵀ R_j A_jᵀ; the root: W R_root A_rootᵀ. The glTF rig (exports/gltf.py)
    animates its nodes with these same rotations.
    """
    art = rec.articulation
    R = rec.rotations @ np.swapaxes(A, -1, -2)[None]  # file frames in the tracker world, (n, m, 3, 3)
    local = np.empty_like(R)
    root = art.root
    local[:, root] = world @ R[:, root]
    child = art.parent >= 0
    local[:, child] = np.swapaxes(R[:, art.parent[child]], -1, -2) @ R[:, child]
    return local


def motion_channels(rec: Reconstruction, world: np.ndarray, scale: float, A: np.ndarray) -> np.ndarray:
    """(n, 3 + 3m) MOTION rows in hierarchy order: root position, then Z X Y angles of every body.

    Local rotation of child j under p: A_p R_pᵀ R_j A_jᵀ; of the root: W R_root A_rootᵀ.
    """
    art = rec.articulation
    root = art.root
    angles = _euler_degrees(local_rotations(rec, world, A)[:, depth_first(art)])  # (n, m, 3)
    position = (rec.joint_positions[:, root] @ world.T) * scale
    return np.concatenate([position, angles.reshape(len(angles), -1)], axis=1)


def hierarchy_text(art: Articulation, scale: float, A: np.ndarray | None = None, names: list[str] | None = None) -> str:
    """The HIERARCHY section: offsets from the fit (A_p (l_j − c_p)), End Sites at leaf sensors."""
    names = names or bvh_names(art.names)
    A = np.broadcast_to(np.eye(3), (art.n_bodies, 3, 3)) if A is None else A
    origin = art.origin()
    lines = ["HIERARCHY"]

    def f(v) -> str:
        return " ".join(f"{x * scale:.6f}" for x in v)

    def emit(i: int, depth: int) -> None:
        pad = "  " * depth
        if i == art.root:
            lines.append(f"{pad}ROOT {names[i]}")
            lines.append(f"{pad}{{")
            lines.append(f"{pad}  OFFSET 0.000000 0.000000 0.000000")
            lines.append(f"{pad}  CHANNELS 6 Xposition Yposition Zposition {' '.join(ROTATION_CHANNELS)}")
        else:
            p = art.parent[i]
            lines.append(f"{pad}JOINT {names[i]}")
            lines.append(f"{pad}{{")
            lines.append(f"{pad}  OFFSET {f(A[p] @ (art.l[i] - origin[p]))}")
            lines.append(f"{pad}  CHANNELS 3 {' '.join(ROTATION_CHANNELS)}")
        kids = art.children(i)
        for j in kids:
            emit(j, depth + 1)
        if not kids:
            # A leaf ends at its sensor, the one point of it the data pins down besides its joint.
            lines.append(f"{pad}  End Site")
            lines.append(f"{pad}  {{")
            lines.append(f"{pad}    OFFSET {f(A[i] @ -origin[i])}")
            lines.append(f"{pad}  }}")
        lines.append(f"{pad}}}")

    emit(art.root, 0)
    return "\n".join(lines) + "\n"


@dataclass(frozen=True)
class Playback:
    """What the BVH and the glTF rig (exports/gltf.py) both write a take through: the articulation in the
    take's sensor order, rigidly attached sensors placed from its frames; the world turn W; the rest frames A;
    and each sensor's first valid pose (held before its first record, carried into the first chunk)."""

    articulation: Articulation
    world: np.ndarray
    A: np.ndarray
    first: tuple[np.ndarray, np.ndarray]
    names: list[str] | None = None  # each body's BVH joint / glTF node name (`node_names`); None: bvh_names

    def chunks(self, take: ChunkedTake, chunk_frames: int | None = None) -> Iterator[Reconstruction]:
        """The take played through the articulation, `chunk_frames` frames at a time (None: the take's own)."""
        return reconstruct_chunks(take.chunks(chunk_frames), self.articulation, self.first)


def playback(calibration, take: ChunkedTake, up: str, rest: str | int) -> Playback:
    """The `Playback` of `take` (a Take, or any ChunkedTake) through `calibration` (a Calibration, its §5
    dict or an Articulation). Reads the take once to place rigid sensors (when there are any), then up to
    each sensor's first valid record and to the rest frame; errors come before any output."""
    world = bvh_world(up)
    art = calibration if isinstance(calibration, Articulation) else articulation(calibration)
    art = art.reordered(take.names)
    if art.incomplete.any():
        art = art.completed(frames=take.chunks())
    first = first_valid(take.chunks())
    return Playback(art, world, rest_frames(take, world, rest, first), first, node_names(calibration, art.names))


def bvh_chunks(calibration, take: ChunkedTake, *, units: str = "cm", up: str = "-z", rest: str | int = "first",
               chunk_frames: int | None = None) -> Iterator[str]:
    """The BVH file for `take` (a flockcal.takes.Take, or any ChunkedTake: the service's frame log) played
    through `calibration` (a Calibration or its §5 dict, or an Articulation), as text: the HIERARCHY and
    MOTION header, then the rows of `chunk_frames` frames at a time (None: the take's own chunks; a Take
    gives all its frames at once). `up` names the tracker world's up axis; the file is Y-up. `rest`: the
    file's rest pose, "first" (the take's first frame), a frame index, or "sensor" (see rest_frames).
    Errors in the options, the calibration or the take are raised by the first next(), before any text."""
    if units not in UNITS_PER_METRE:
        raise BvhError(f"units must be one of {', '.join(UNITS_PER_METRE)}, got {units!r}")
    scale = UNITS_PER_METRE[units]
    pb = playback(calibration, take, up, rest)
    yield (hierarchy_text(pb.articulation, scale, pb.A, pb.names)
           + f"MOTION\nFrames: {take.n_frames}\nFrame Time: {1.0 / take.rate_hz:.8f}\n")
    for rec in pb.chunks(take, chunk_frames):
        out = io.StringIO()
        np.savetxt(out, motion_channels(rec, pb.world, scale, pb.A), fmt="%.6f")
        yield out.getvalue()


def bvh_text(calibration, take, *, units: str = "cm", up: str = "-z", rest: str | int = "first") -> str:
    """The whole BVH file as one string (`bvh_chunks` joined)."""
    return "".join(bvh_chunks(calibration, take, units=units, up=up, rest=rest))


def bvh_bytes(calibration, take, **options) -> bytes:
    """`bvh_text` encoded for a download (ASCII)."""
    return bvh_text(calibration, take, **options).encode("ascii")


def write_bvh(path: str | os.PathLike, calibration, take, **options) -> None:
    """Write the BVH file to `path` a chunk of frames at a time (atomically: a failure never leaves a
    half-written file)."""
    write_pieces(path, bvh_chunks(calibration, take, **options), encoding="ascii")
