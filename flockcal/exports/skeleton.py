"""Skeleton file export: a calibration written as the versioned JSON of flockcal/skeleton.py, and read back.

`skeleton_dict`/`write_skeleton` turn a Calibration into the file (the tree, joint centres in both bodies'
frames, bones, placements, the source take); `load_skeleton` validates one, tree and bones included, and
says what is wrong. The file's format and structural checks are the base layer's (flockcal/skeleton.py), the
`Skeleton` it builds the solver's (flockcal.solver.known_skeleton).
"""

from __future__ import annotations

import json
import os
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from flockcal.atomic import write_atomic
from flockcal.skeleton import FORMAT, VERSION, SkeletonError, check_skeleton_data, json_safe
from flockcal.solver.known_skeleton import Skeleton
from flockcal.solver.known_skeleton import bones as bones_of
from flockcal.solver.reconstruct import ArticulationError, articulation

def skeleton_dict(calibration, source: dict | None = None, take=None, acc=None) -> dict:
    """The skeleton file's content for a Calibration (or its §5 dict); `source` describes the take
    (e.g. {"take": "walk.npz", "frames": n, "rate_hz": r}); sessions may add their own keys.

    A sensor rigidly attached to its parent (a calibration's `rigid_groups`) has no fitted joint; the
    file then pins it at its own sensor, which needs the `take` (a Take, or any `flockcal.takes.ChunkedTake`:
    the service's frame log, read a chunk at a time) or its accumulator `acc`.
    """
    d = calibration.to_dict() if hasattr(calibration, "to_dict") else dict(calibration)
    art = articulation(d)
    if art.incomplete.any():
        if take is not None:
            art = art.reordered(take.names).completed(frames=take.chunks()).reordered(art.names)
        elif acc is not None:
            art = art.completed(acc=acc)
        else:
            rigid = ", ".join(art.names[i] for i in np.flatnonzero(art.incomplete))
            raise SkeletonError(f"sensor(s) {rigid} ride rigidly on their parent; pass the take or its accumulator to place them")
    names = art.names
    joint_of = {j["child"]: j for j in d["joints"] if d["parent"].get(j["child"]) == j["parent"]}
    for i in np.flatnonzero(art.rigid if art.rigid is not None else np.zeros(len(names), bool)):
        joint_of[names[i]] = {"child": names[i], "parent": names[art.parent[i]], "c": art.c[i].tolist(),
                              "l": art.l[i].tolist(), "rigid": True, "hinge": False}
    placements = []
    bodies = []
    for i, name in enumerate(names):
        inboard = art.parent[i] >= 0
        placements.append(
            {
                "sensor": name,
                "joint": name if inboard else None,
                # The sensor sits at −c from its inboard joint: c is the joint in the sensor's frame.
                "joint_in_sensor_frame_m": art.c[i].tolist() if inboard else None,
                "distance_m": float(np.linalg.norm(art.c[i])) if inboard else None,
                "stderr_m": joint_of.get(name, {}).get("c_stderr_m"),
            }
        )
        points = [{"joint": name, "position_m": art.c[i].tolist()}] if inboard else []
        points += [{"joint": names[k], "position_m": art.l[k].tolist()} for k in art.children(i)]
        bodies.append({"body": name, "joints": points})
    return {
        "format": FORMAT,
        "version": VERSION,
        "units": "m",
        "created_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "source": dict(source or {}),
        "sensors": list(names),
        "root": names[art.root],
        "parent": {names[j]: names[art.parent[j]] for j in art.order[1:]},
        "joints": [joint_of[names[j]] for j in art.order[1:]],
        "bones": _measured_bones(d, art),
        "rigid_groups": d.get("rigid_groups") or [],
        "placements": placements,
        "bodies": bodies,
    }


def _measured_bones(d: dict, art) -> list[dict]:
    """The calibration's bones (only the ones it measured: a bone ending at an undetermined joint was not),
    each as long as the joint centres the file holds make it: what `parse_skeleton` checks. A result stored
    before the slip refit measured its bones between those centres (solver/segments.py) could hold a
    forearm 2 mm off them; its file is whole all the same."""
    if "bones" not in d:
        return bones_of(art)
    between = {(b["body"], frozenset((b["from_joint"], b["to_joint"]))): b["length_m"] for b in bones_of(art)}
    out = []
    for b in d["bones"]:
        key = (b.get("body"), frozenset((b.get("from_joint"), b.get("to_joint"))))
        out.append(dict(b, length_m=between[key]) if key in between else dict(b))
    return out


def skeleton_bytes(calibration, source: dict | None = None, take=None, acc=None) -> bytes:
    """The skeleton file as UTF-8 JSON bytes (for a download)."""
    return (json.dumps(json_safe(skeleton_dict(calibration, source, take, acc)), indent=2) + "\n").encode("utf-8")


def write_skeleton(path: str | os.PathLike, calibration, source: dict | None = None, take=None, acc=None) -> None:
    """Write the skeleton file to `path` (atomically)."""
    write_atomic(path, skeleton_bytes(calibration, source, take, acc))


def parse_skeleton(data, origin: str = "skeleton") -> Skeleton:
    """Validate skeleton content (JSON text, bytes or a dict); SkeletonError names the first problem."""
    data = check_skeleton_data(data, origin)
    names = data["sensors"]
    try:
        art = articulation(data)
    except ArticulationError as exc:
        raise SkeletonError(f"{origin}: {exc}") from None
    if data.get("root") is not None and data["root"] != names[art.root]:
        raise SkeletonError(f"{origin}: 'root' is {data['root']!r} but the parent map is rooted at {names[art.root]!r}")
    # Bones are derived from the joint centres; a stated length that disagrees means the file was edited
    # inconsistently. (Bones the file does not list, e.g. inside a rigid group, are not required.)
    stated = {}
    for b in data["bones"]:
        if isinstance(b, dict):
            stated[(b.get("from_joint"), b.get("to_joint"))] = b.get("length_m")
    for bone in bones_of(art):
        key = (bone["from_joint"], bone["to_joint"])
        if key not in stated and key[::-1] not in stated:
            continue
        length = stated.get(key, stated.get(key[::-1]))
        if not isinstance(length, (int, float)) or abs(length - bone["length_m"]) > 1e-6:
            raise SkeletonError(
                f"{origin}: bone {key[0]}→{key[1]} on {bone['body']} is {length!r} m in 'bones' but the joint "
                f"centres give {bone['length_m']:.6f} m; the file was edited inconsistently — re-export it"
            )
    return Skeleton(data, art)


def load_skeleton(path: str | os.PathLike) -> Skeleton:
    """Read and validate a skeleton file; SkeletonError for a missing, corrupt or inconsistent file."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise SkeletonError(f"{path}: no such skeleton file") from None
    except OSError as exc:
        raise SkeletonError(f"{path}: cannot read ({exc.strerror})") from None
    return parse_skeleton(raw, origin=str(path))


__all__ = ["FORMAT", "VERSION", "Skeleton", "SkeletonError", "load_skeleton", "parse_skeleton", "skeleton_bytes",
           "skeleton_dict", "write_skeleton"]
