"""Where a hinge's centre sits on its axis: the data fix the axis but not the point along it, so a rule
does (docs/design.md §3c). One rule for every tree of joints — the sensor path live and offline, and the
optical path: where the limb's bones meet the hinge axis, judged from the neighbouring joints.
"""

from __future__ import annotations

import numpy as np

# How far the true centre may lie from each rule's point, as a standard deviation: where the limb's bones
# meet the axis is the centre up to the bones' own bend about it (the simulated elbows and knees lie within
# 6 mm of it on exact neighbours; the known-skeleton fit counts it as a measurement with this sd); the
# minimum-norm point is only "closest to the sensor origins", and skin sensors sit 2–8 cm to one side of
# the bone.
LIMB_RULE_SD_M = 0.005
MIN_NORM_SD_M = 0.05

# A neighbouring joint places the hinge only when the bone to it makes at least this angle with the
# hinge axis: the foot of a perpendicular from a point nearly on the axis's own line is ill-conditioned.
# 45°: the foot then moves no more along the axis than the neighbour's centre moves across it.
MIN_BONE_AXIS_ANGLE = np.radians(45.0)


def hinge_offsets(pairs: np.ndarray, c: np.ndarray, l: np.ndarray, axis_child: np.ndarray,
                  axis_parent: np.ndarray, hinge: np.ndarray, determined: np.ndarray,
                  ls_offset: np.ndarray | None = None, ls_error: np.ndarray | None = None
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """How far (J,) to slide each tree joint along its own axis, by which rule (J,) it is placed, and the
    share (J,) of the data's own least-squares point in it.

    pairs (J, 2): (child, parent) sensor indices of the tree's joints; c, l (J, 3): each joint's centre in
    its child's and its parent's frame; axis_child, axis_parent (J, 3): a hinge's axis in the two frames
    (unit, the same world axis); hinge, determined (J,) bool; ls_offset, ls_error (J,): the least-squares
    point along the axis as a slide from c, and its error (`PairFits.axis_offset`, `direction_error[:, 0]`;
    NaN / inf where the axis saw no rotation beyond noise). The new centre is c + s a_child, l + s a_parent.

    Rule ("feet", docs/design.md §3c): a hinge joins two bodies; each of them that is a limb segment
    (exactly two joints) whose other joint is determined — a ball joint, or a hinge already placed by this
    rule — gives the foot of the perpendicular from that joint's centre onto the hinge axis, in that body's
    frame (along the axis f, the distance r of that joint from the axis). With two, the hinge sits at
    (r₁f₀ + r₀f₁)/(r₀ + r₁): the point from which both bones make the same angle with the axis, where the
    limb's line crosses the axis once each bone is turned about it into one plane; an axis tilted along the
    limb (a carrying angle) then cancels whatever the bones' lengths (the plain mean of the feet cancels
    it only for equal bones). With one, its foot. Chains of hinges are placed outward from the ball
    joints, a hinge counting as a neighbour once it is placed itself. A hinge with no such neighbour keeps
    the minimum-norm point of its axis (the paper's "closest to the sensor origins").

    The data's own least-squares point counts only for the minimum-norm fallback, averaged with it by
    weights 1/sd² (MIN_NORM_SD_M and the least-squares error): a real knee whose axis point the trial pins
    to 6 mm, with no determined neighbour, keeps its measured point. Next to the limb rule it does not
    count: along a barely turned axis under soft tissue it is off by centimetres while its stated error,
    read from a routine that repeats, says millimetres (docs/design.md §3c has the figures).

    Returns (s, how, share): how is 2 or 1 (feet used), 0 (minimum-norm) or -1 (not a hinge: s = 0).
    """
    P = np.asarray(pairs, dtype=np.intp).reshape(-1, 2)
    J = len(P)
    s = np.zeros(J)
    how = np.full(J, -1)
    share = np.zeros(J)
    hinge = np.asarray(hinge, dtype=bool) & np.asarray(determined, dtype=bool)
    if not hinge.any():
        return s, how, share
    ls = np.full(J, np.nan) if ls_offset is None else np.asarray(ls_offset, dtype=float)
    err = np.full(J, np.inf) if ls_error is None else np.asarray(ls_error, dtype=float)
    usable = np.isfinite(ls) & np.isfinite(err) & (err > 0)

    def blended(k: int, rule_s: float, rule_sd: float) -> float:
        if not usable[k]:
            return rule_s
        share[k] = rule_sd**2 / (rule_sd**2 + err[k] ** 2)
        return float(rule_s + share[k] * (ls[k] - rule_s))

    a = np.stack([axis_child, axis_parent], axis=1)  # (J, 2, 3): the axis in the child's (0) and parent's (1) frame
    x = np.stack([c, l], axis=1)  # (J, 2, 3): the centre in the same two frames
    # The joints of every body, in that body's frame: joint k is at x[k, 0] in sensor P[k, 0], x[k, 1] in P[k, 1].
    body_joints: dict[int, list[tuple[int, int]]] = {}
    for k, (ch, pa) in enumerate(P.tolist()):
        body_joints.setdefault(ch, []).append((k, 0))
        body_joints.setdefault(pa, []).append((k, 1))
    placed = np.asarray(determined, dtype=bool) & ~hinge  # anchors: determined ball joints
    todo = set(np.flatnonzero(hinge).tolist())
    while todo:
        now = {}
        for k in sorted(todo):
            feet = []
            for side in (0, 1):
                others = [(o, so) for o, so in body_joints[int(P[k, side])] if o != k]
                if len(others) != 1:
                    continue  # a leaf (no bone) or a hub (no one long axis)
                o, so = others[0]
                if not placed[o]:
                    continue
                d = x[o, so] + (s[o] * a[o, so] if how[o] > 0 else 0.0) - x[k, side]
                along = float(d @ a[k, side])
                across = float(np.linalg.norm(d - along * a[k, side]))
                if abs(along) * np.tan(MIN_BONE_AXIS_ANGLE) > across:
                    continue  # the bone runs too nearly along the axis to say where it meets it
                feet.append((along, across))
            if len(feet) == 2:
                # Each bone weighted by the other's length: the point from which both bones make the same
                # angle with the axis, so an axis tilted along the limb (a carrying angle) cancels whatever
                # the two bones' lengths; the plain mean of the feet cancels it only for equal bones.
                (f0, r0), (f1, r1) = feet
                now[k] = ((r1 * f0 + r0 * f1) / (r0 + r1), 2)
            elif feet:
                now[k] = (feet[0][0], 1)
        if not now:
            break
        for k, (sk, n) in now.items():  # placed together: a pass sees only the passes before it
            s[k], how[k], placed[k] = sk, n, True
            todo.discard(k)
    for k in todo:  # no placed neighbour anywhere along its chain: the minimum-norm point of the axis line
        s[k] = blended(k, -float(x[k, 0] @ a[k, 0] + x[k, 1] @ a[k, 1]) / 2.0, MIN_NORM_SD_M)
        how[k] = 0
    return s, how, share
