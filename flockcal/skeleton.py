"""The saved-skeleton file's format: its name and version, its errors and its structural checks.

Base layer: the server's skeleton library, the solver's saved-skeleton fit and the exports share it.
Checks that need the solver (one tree, bones that agree with the joint centres) are the exports'
`parse_skeleton`, which builds the solver's `Skeleton` (flockcal.solver.known_skeleton) that `known_fit` fits with.
"""

from __future__ import annotations

import json
import math

import numpy as np

from flockcal.errors import FlockcalError

FORMAT = "flockcal-skeleton"
VERSION = 1


class SkeletonError(FlockcalError, ValueError):
    """A skeleton file that is unreadable, malformed, or made for other sensors."""


class SkeletonRangeError(SkeletonError):
    """A number in a skeleton file that is not finite or not a body's size (the API answers 422)."""


# A body is metres: a joint this far from its sensor, or a bone this long, is a damaged or hostile file
# (a centre of [1e200, 0, 0] overflowed the fit into a 500 and kept the service from starting).
MAX_BODY_M = 10.0


def _vec3(value, where: str) -> list[float]:
    if not isinstance(value, (list, tuple)) or len(value) != 3:
        raise SkeletonError(f"{where} must be a list of 3 numbers")
    try:
        out = [float(x) for x in value]
    except (TypeError, ValueError, OverflowError):
        raise SkeletonError(f"{where} must be a list of 3 numbers") from None
    if not all(math.isfinite(x) for x in out):
        raise SkeletonRangeError(f"{where} holds a non-finite number")
    if math.hypot(*out) > MAX_BODY_M:
        raise SkeletonRangeError(f"{where} is {math.hypot(*out):.3g} m from its sensor; a joint lies within "
                            f"{MAX_BODY_M:g} m of it (a body is metres): the file is damaged — re-export it")
    return out


def _length(value, where: str) -> None:
    """A bone's stated length or standard error: absent, null, or metres within MAX_BODY_M."""
    if value is None:
        return
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(float(value)) \
            or not 0 <= float(value) <= MAX_BODY_M:
        raise SkeletonRangeError(f"{where} must be a length from 0 to {MAX_BODY_M:g} m, got {str(value)[:40]}")


def check_skeleton_data(data, origin: str = "skeleton") -> dict:
    """The skeleton content (JSON text, bytes or a dict) as a dict whose format, version, names and joint
    vectors are sound (joint c and l made lists of floats); SkeletonError names the first problem."""
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
    for k, bone in enumerate(data["bones"]):
        if not isinstance(bone, dict) or not isinstance(bone.get("to_joint"), str):
            raise SkeletonError(f"{origin}: bones[{k}] needs 'to_joint' (and 'from_joint', 'length_m')")
        _length(bone.get("length_m"), f"{origin}: bones[{k}].length_m")
        _length(bone.get("stderr_m"), f"{origin}: bones[{k}].stderr_m")
    return data


def json_safe(obj):
    """NaN/inf become null: JSON has no NaN, and a reader in another language must not choke on it."""
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if isinstance(obj, dict):
        return {k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, np.generic):
        return json_safe(obj.item())
    return obj
