"""Readable names for sensors and joints: 'l_forearm' → 'left forearm', the joint it ends → 'left elbow';
and the humanoid bones a sensor's name implies ('l_forearm' → leftLowerArm), checked against the data's finding.

Base layer: the CLI tables, the report and the progress hints all name things the same way; the
dashboard's pages read the table here too, as the script the service makes of it (/static/names.js).
"""

from __future__ import annotations

import re
from functools import lru_cache

# Body keyword → the joint at its inboard end, and how far out along the body that joint sits: a joint is
# named after the more distal of its two bodies, whichever way the tree happens to be rooted (docs/design.md §5
# names a joint by its child, and the fitted tree's root need not be the pelvis). The pages' jointLabel
# reads it from the service (server/app.py serves it as /static/names.js), so patterns are JavaScript too.
BODY_JOINTS = [
    (r"hand|wrist", "wrist", 5), (r"foot|ankle", "ankle", 5), (r"toe", "toes", 6), (r"head", "neck", 5),
    (r"fore ?arm|lower ?arm", "elbow", 4), (r"shin|shank|calf|lower ?leg|low ?leg|tibia", "knee", 4),
    (r"upper ?arm|up ?arm|humerus|\barm\b", "shoulder", 3), (r"thigh|upper ?leg|up ?leg|femur", "hip", 3),
    (r"neck", "lower neck", 3), (r"clavicle|shoulder", "collarbone", 2),
    (r"chest|thorax|upper ?back", "mid back", 2), (r"abdomen|spine|torso|back|waist", "lower back", 1),
    (r"pelvis|hips?\b", "lower back", 0),
]


# Names are a session's few sensors, asked about on every fit (~30/s): worked out once each.
@lru_cache(maxsize=1024)
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


@lru_cache(maxsize=1024)
def _body_joint(name: str) -> tuple[str, int] | None:
    body = readable_body(name)
    side = ""
    for s in ("left ", "right "):
        if body.startswith(s):
            side, body = s, body[len(s):]
    for pattern, joint, rank in BODY_JOINTS:
        if re.search(pattern, body):
            return f"{side}{joint}", rank
    return None


def joint_name(child: str, parent: str | None) -> str:
    """The joint between `parent` and `child` as people name it ('left elbow'), the same whichever of the
    two bodies the fit made the child; bodies with no known name give 'parent–child' ('bird 1–bird 2')."""
    a = _body_joint(child)
    b = _body_joint(parent) if parent else None
    if a and (not b or a[1] >= b[1]):
        return a[0]
    if b:
        return b[0]
    return f"{readable_body(parent)}–{readable_body(child)}" if parent else readable_body(child)


def names_joint(child: str, parent: str | None) -> bool:
    """Whether `joint_name` reads a body part from either name ('left elbow'), not just joins the two."""
    return bool(_body_joint(child) or (parent and _body_joint(parent)))


def joint_label(child: str, parent: str | None) -> str:
    """The joint's name for a sentence: 'the left elbow', 'the joint between the bird 1 and the bird 2'."""
    if names_joint(child, parent):
        return f"the {joint_name(child, parent)}"
    if not parent:
        return f"the {readable_body(child)}"
    return f"the joint between the {readable_body(parent)} and the {readable_body(child)}"


# Body keyword → the humanoid bones (VRM 1.0 names; a limb's without its side) a sensor so named implies. A
# name that may mean more than one segment implies each ("arm": Mixamo's LeftArm is the upper arm, a person's
# "left arm" the whole limb), so only a bone outside them contradicts it. First match wins: "forearm"
# before "arm", "upper leg" before "leg".
BODY_BONES = [
    (r"hand|wrist|palm|finger", ("Hand",)), (r"foot|ankle|toe|heel", ("Foot",)), (r"head|skull", ("head",)),
    (r"fore ?arm|lower ?arm|low ?arm|radius|ulna", ("LowerArm",)),
    (r"shin|shank|calf|lower ?leg|low ?leg|tibia", ("LowerLeg",)),
    (r"upper ?arm|up ?arm|humerus", ("UpperArm",)), (r"thigh|upper ?leg|up ?leg|femur", ("UpperLeg",)),
    (r"\barm\b", ("UpperArm", "LowerArm")), (r"\bleg\b", ("UpperLeg", "LowerLeg")),
    (r"chest|thorax|upper ?back|sternum|breast", ("chest",)),
    (r"abdomen|spine|waist|belly|lower ?back|lumbar|torso", ("spine", "chest")),
    (r"pelvis|hips?\b|sacrum|buttock", ("hips",)),
]


@lru_cache(maxsize=1024)
def named_bones(name: str) -> tuple[str, ...]:
    """The humanoid bones (VRM 1.0 names) sensor `name` implies: 'l_forearm' → ('leftLowerArm',), 'RightUpLeg'
    → ('rightUpperLeg',), 'forearm' → both forearms, 'left leg' → left thigh and shin; () for a name that says
    no body part ('bird 3'). A limb's side comes from the name ('l', 'left', 'LeftHand', 'r shin'), trunk
    and head have none."""
    body = readable_body(name)
    sides = ("left", "right")
    for s in sides:
        if body.startswith(s + " "):
            sides, body = (s,), body[len(s) + 1:]
    for pattern, bones in BODY_BONES:
        if re.search(pattern, body):
            return tuple(b if b[0].islower() else s + b for b in bones for s in (sides if b[0].isupper() else ("",)))
    return ()
