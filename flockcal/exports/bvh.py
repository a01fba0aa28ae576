"""BVH export of a take played back through its calibration (Blender, MotionBuilder, Maya import it).

Each body's BVH frame is its sensor frame, pivoting at its inboard joint; the root pivots at its sensor
and carries the position channels. Centimetres in the file, SI everywhere else; Y is up in the file.
"""

from __future__ import annotations

import io
import os
import re
import warnings
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from flockcal.solver.reconstruct import Articulation, Reconstruction, articulation, reconstruct

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
        raise ValueError(f"up must be one of {', '.join(UP_AXES)}, got {up!r}") from None


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


def motion_channels(rec: Reconstruction, world: np.ndarray, scale: float) -> np.ndarray:
    """(n, 3 + 3m) MOTION rows in hierarchy order: root position, then Z X Y angles of every body."""
    art = rec.articulation
    R = rec.rotations
    local = np.empty_like(R)
    root = art.root
    local[:, root] = world @ R[:, root]
    child = art.parent >= 0
    local[:, child] = np.swapaxes(R[:, art.parent[child]], -1, -2) @ R[:, child]
    angles = _euler_degrees(local[:, depth_first(art)])  # (n, m, 3)
    position = (rec.joint_positions[:, root] @ world.T) * scale
    return np.concatenate([position, angles.reshape(len(R), -1)], axis=1)


def hierarchy_text(art: Articulation, scale: float, names: list[str] | None = None) -> str:
    """The HIERARCHY section: offsets from the fit (l_j − c_parent), End Sites at leaf sensors."""
    names = names or bvh_names(art.names)
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
            lines.append(f"{pad}JOINT {names[i]}")
            lines.append(f"{pad}{{")
            lines.append(f"{pad}  OFFSET {f(art.l[i] - origin[art.parent[i]])}")
            lines.append(f"{pad}  CHANNELS 3 {' '.join(ROTATION_CHANNELS)}")
        kids = art.children(i)
        for j in kids:
            emit(j, depth + 1)
        if not kids:
            # A leaf ends at its sensor, the one point of it the data pins down besides its joint.
            lines.append(f"{pad}  End Site")
            lines.append(f"{pad}  {{")
            lines.append(f"{pad}    OFFSET {f(-origin[i])}")
            lines.append(f"{pad}  }}")
        lines.append(f"{pad}}}")

    emit(art.root, 0)
    return "\n".join(lines) + "\n"


def bvh_text(calibration, take, *, units: str = "cm", up: str = "-z") -> str:
    """The BVH file for `take` (a flockcal.takes.Take) played through `calibration` (a Calibration or its
    §5 dict, or an Articulation). `up` names the tracker world's up axis; the file is Y-up."""
    if units not in UNITS_PER_METRE:
        raise ValueError(f"units must be one of {', '.join(UNITS_PER_METRE)}, got {units!r}")
    scale = UNITS_PER_METRE[units]
    world = bvh_world(up)
    art = calibration if isinstance(calibration, Articulation) else articulation(calibration)
    art = art.reordered(take.names)
    rec = reconstruct(take.rotations, take.positions, art, take.valid)
    art = rec.articulation  # rigidly attached sensors now have their offsets
    rows = motion_channels(rec, world, scale)
    out = io.StringIO()
    out.write(hierarchy_text(art, scale))
    out.write("MOTION\n")
    out.write(f"Frames: {len(rows)}\n")
    out.write(f"Frame Time: {1.0 / take.rate_hz:.8f}\n")
    np.savetxt(out, rows, fmt="%.6f")
    return out.getvalue()


def bvh_bytes(calibration, take, **options) -> bytes:
    """`bvh_text` encoded for a download (ASCII)."""
    return bvh_text(calibration, take, **options).encode("ascii")


def write_bvh(path: str | os.PathLike, calibration, take, **options) -> None:
    """Write the BVH file to `path` (atomically: a failure never leaves a half-written file)."""
    path = Path(path)
    text = bvh_text(calibration, take, **options)
    tmp = path.with_name(path.name + ".part")
    tmp.write_text(text, encoding="ascii")
    os.replace(tmp, path)
