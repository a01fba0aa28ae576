"""Plain-language coaching from a fit: which joints need more movement, and overall progress in [0, 1].

Coverage per axis is 1 − σ_k(M) (design.md §3). A hinge needs its own axis exercised; a ball joint's centre
is pinned once it has turned about two axes (twist about the third adds nothing to the centre). A joint is
done when that coverage and its standard error both reach their targets — the same rule the pages apply.
"""

from __future__ import annotations

import math
import re

# 1 − σ(M) on a needed axis counted as "moved enough" (≈ 8° rms; the pages' `coverage` default). The
# standard-error target, not this, decides how much more data a joint needs.
COVERAGE_FULL = 0.01
STDERR_TARGET_M = 0.005  # joint centre uncertainty counted as calibrated

# The joint is named by its child body; people name it by the joint itself.
_JOINT_OF_BODY = [
    (r"fore ?arm|lower ?arm", "elbow"),
    (r"upper ?arm|up ?arm|humerus|\barm\b", "shoulder"),
    (r"hand|wrist", "wrist"),
    (r"shin|shank|calf|lower ?leg|low ?leg|tibia", "knee"),
    (r"thigh|upper ?leg|up ?leg|femur", "hip"),
    (r"foot|ankle", "ankle"),
    (r"toe", "toes"),
    (r"head", "neck"),
    (r"neck", "lower neck"),
    (r"clavicle|shoulder", "collarbone"),
    (r"chest|thorax|upper ?back", "upper back"),
    (r"spine|torso|back|abdomen|pelvis|hips?\b", "lower back"),
]


def readable_body(name: str) -> str:
    """'l_forearm' → 'left forearm', 'RightUpLeg' → 'right up leg', 'bird3' → 'bird 3'."""
    s = re.sub(r"([a-z])([A-Z])", r"\1 \2", str(name))
    s = re.sub(r"([A-Za-z])(\d)", r"\1 \2", s)
    words = [w for w in re.split(r"[\s_.\-]+", s) if w]
    out = []
    for k, w in enumerate(words):
        lw = w.lower()
        if lw in ("l", "lt") and (k == 0 or k == len(words) - 1):
            out.append("left")
        elif lw in ("r", "rt") and (k == 0 or k == len(words) - 1):
            out.append("right")
        else:
            out.append(lw)
    if out and out[-1] in ("left", "right") and len(out) > 1:
        out = [out[-1]] + out[:-1]
    return " ".join(out)


def joint_label(child: str, parent: str) -> str:
    """Readable name of the joint between `parent` and its child body `child` ('the left elbow')."""
    body = readable_body(child)
    side = ""
    for s in ("left ", "right "):
        if body.startswith(s):
            side, body = s, body[len(s):]
    for pattern, joint in _JOINT_OF_BODY:
        if re.search(pattern, body):
            return f"the {side}{joint}"
    return f"the joint between the {readable_body(parent)} and the {readable_body(child)}"


def needed_coverage(joint: dict) -> float:
    """Coverage of the axes the joint needs: a hinge's largest, a ball joint's second largest."""
    cov = sorted(float(x) for x in joint.get("coverage") or (0.0, 0.0, 0.0))
    return cov[-1] if joint.get("hinge") else cov[-2]


def joint_progress(joint: dict) -> float:
    needed = needed_coverage(joint)
    c = min(1.0, max(0.0, needed / COVERAGE_FULL))
    err = max(float(joint.get("c_stderr_m") or math.inf), float(joint.get("l_stderr_m") or math.inf))
    u = min(1.0, STDERR_TARGET_M / max(err, 1e-12)) if math.isfinite(err) else 0.0
    return min(c, u)


def hints(fit: dict) -> list[dict]:
    """One sentence per joint that needs more movement, weakest first: {joint, progress, hint}."""
    out = []
    for j in fit.get("joints", []):
        p = joint_progress(j)
        if p >= 1.0:
            continue
        cov = [float(x) for x in j.get("coverage") or (0.0, 0.0, 0.0)]
        label = joint_label(j["child"], j["parent"])
        if max(cov) < COVERAGE_FULL / 3:
            text = f"Move {label} more: it has hardly turned yet."
        elif needed_coverage(j) < COVERAGE_FULL:
            text = f"Move {label} more, in other directions too (twist and swing it, not only bend)."
        else:
            text = f"Keep moving {label}: a little more and it is pinned down."
        out.append({"joint": j["child"], "label": label, "progress": round(p, 3), "hint": text})
    out.sort(key=lambda h: h["progress"])
    return out


def progress(fit: dict) -> float:
    """Overall progress in [0, 1]: the mean of the joints' progress (0 with no joints yet)."""
    joints = fit.get("joints", [])
    if not joints:
        return 0.0
    return round(sum(joint_progress(j) for j in joints) / len(joints), 4)
