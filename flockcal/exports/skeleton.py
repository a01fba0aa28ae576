"""Skeleton file: the calibrated performer as versioned JSON, to fit their next take with it.

Holds the tree, joint centres in both bodies' frames, bones, sensor placements, hinge axes and
uncertainties, and the take it came from. `load_skeleton` validates it and says what is wrong.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from flockcal.atomic import write_atomic
from flockcal.errors import FlockcalError
from flockcal.solver.known_skeleton import bones as bones_of
from flockcal.solver.reconstruct import Articulation, ArticulationError, articulation

FORMAT = "flockcal-skeleton"
VERSION = 1


class SkeletonError(FlockcalError, ValueError):
    """A skeleton file that is unreadable, malformed, or made for other sensors."""


def skeleton_dict(calibration, source: dict | None = None, take=None, acc=None) -> dict:
    """The skeleton file's content for a Calibration (or its §5 dict); `source` describes the take
    (e.g. {"take": "walk.npz", "frames": n, "rate_hz": r}); sessions may add their own keys.

    A sensor rigidly attached to its parent (a calibration's `rigid_groups`) has no fitted joint; the
    file then pins it at its own sensor, which needs the `take` (a Take) or its accumulator `acc`.
    """
    d = calibration.to_dict() if hasattr(calibration, "to_dict") else dict(calibration)
    art = articulation(d)
    if art.incomplete.any():
        if take is not None:
            art = art.reordered(take.names).completed(take.rotations, take.positions, take.valid).reordered(art.names)
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
        # Only the bones the calibration measured: a bone ending at an undetermined joint was not.
        "bones": d["bones"] if "bones" in d else bones_of(art),
        "rigid_groups": d.get("rigid_groups") or [],
        "placements": placements,
        "bodies": bodies,
    }


def _json_safe(obj):
    """NaN/inf become null: JSON has no NaN, and a reader in another language must not choke on it."""
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, dict):
        return {k: _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_safe(v) for v in obj]
    if isinstance(obj, np.generic):
        return _json_safe(obj.item())
    return obj


def skeleton_bytes(calibration, source: dict | None = None, take=None, acc=None) -> bytes:
    """The skeleton file as UTF-8 JSON bytes (for a download)."""
    return (json.dumps(_json_safe(skeleton_dict(calibration, source, take, acc)), indent=2) + "\n").encode("utf-8")


def write_skeleton(path: str | os.PathLike, calibration, source: dict | None = None, take=None, acc=None) -> None:
    """Write the skeleton file to `path` (atomically)."""
    write_atomic(path, skeleton_bytes(calibration, source, take, acc))


@dataclass(frozen=True)
class Skeleton:
    """A validated skeleton file: the saved tree, ready to fit a new take of the same performer."""

    data: dict
    articulation: Articulation

    @property
    def names(self) -> tuple[str, ...]:
        return self.articulation.names

    @property
    def root(self) -> str:
        return self.articulation.names[self.articulation.root]

    @property
    def hierarchy(self) -> dict[str, str]:
        """{child: parent}, root omitted: what `calibrate(..., hierarchy=)` and `--hierarchy` take."""
        return dict(self.data["parent"])

    @property
    def bone_stderr(self) -> dict[tuple[str, str], float]:
        out = {}
        for b in self.data["bones"]:
            if isinstance(b.get("stderr_m"), (int, float)):
                out[(b["from_joint"], b["to_joint"])] = out[(b["to_joint"], b["from_joint"])] = float(b["stderr_m"])
        return out

    @property
    def bone_keys(self) -> frozenset:
        """(from_joint, to_joint) of every bone the file holds: the ones its take measured."""
        return frozenset((b["from_joint"], b["to_joint"]) for b in self.data["bones"])

    def check_names(self, names) -> None:
        """SkeletonError unless the take's sensors are exactly the skeleton's (any order)."""
        try:
            self.articulation.reordered(names)
        except ArticulationError as exc:
            raise SkeletonError(f"skeleton does not match the take: {exc}") from None

    def fit(self, acc, names, previous=None):
        """Fit an accumulated take (sensor order `names`) with this skeleton -> KnownFit (`.to_dict()` §5).

        Live refreshes pass the last KnownFit as `previous` to start from it.
        """
        from flockcal.solver.known_skeleton import fit_known_skeleton

        self.check_names(names)
        return fit_known_skeleton(acc, self.articulation, names, bone_stderr=self.bone_stderr, previous=previous,
                                  bone_keys=self.bone_keys)


def _vec3(value, where: str) -> list[float]:
    if not isinstance(value, (list, tuple)) or len(value) != 3:
        raise SkeletonError(f"{where} must be a list of 3 numbers")
    try:
        out = [float(x) for x in value]
    except (TypeError, ValueError):
        raise SkeletonError(f"{where} must be a list of 3 numbers") from None
    if not all(math.isfinite(x) for x in out):
        raise SkeletonError(f"{where} holds a non-finite number")
    return out


def parse_skeleton(data, origin: str = "skeleton") -> Skeleton:
    """Validate skeleton content (JSON text, bytes or a dict); SkeletonError names the first problem."""
    if isinstance(data, (bytes, str)):
        try:
            data = json.loads(data)
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise SkeletonError(f"{origin}: not valid JSON ({exc})") from None
    if not isinstance(data, dict):
        raise SkeletonError(f"{origin}: a skeleton file holds one JSON object")
    if data.get("format") != FORMAT:
        raise SkeletonError(
            f"{origin}: not a flockcal skeleton file (format is {data.get('format')!r}, expected {FORMAT!r}); "
            "write one with `flockcal skeleton TAKE -o FILE`"
        )
    version = data.get("version")
    if not isinstance(version, int) or version < 1:
        raise SkeletonError(f"{origin}: 'version' must be a positive integer, got {version!r}")
    if version > VERSION:
        raise SkeletonError(
            f"{origin}: skeleton format version {version} is newer than this flockcal reads ({VERSION}); upgrade flockcal"
        )
    for key, kind in (("sensors", list), ("parent", dict), ("joints", list), ("bones", list)):
        if not isinstance(data.get(key), kind):
            raise SkeletonError(f"{origin}: missing or malformed {key!r} ({kind.__name__} expected)")
    names = data["sensors"]
    if not names or not all(isinstance(x, str) and x.strip() for x in names):
        raise SkeletonError(f"{origin}: 'sensors' must be a non-empty list of names")
    if len(set(names)) != len(names):
        raise SkeletonError(f"{origin}: sensor names repeat")
    for k, joint in enumerate(data["joints"]):
        if not isinstance(joint, dict) or "child" not in joint or "parent" not in joint:
            raise SkeletonError(f"{origin}: joints[{k}] needs 'child' and 'parent'")
        joint["c"] = _vec3(joint.get("c"), f"{origin}: joints[{k}].c")
        joint["l"] = _vec3(joint.get("l"), f"{origin}: joints[{k}].l")
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
