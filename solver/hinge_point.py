"""Where a hinge's centre sits on its axis: the data fix the axis but not the point along it, so a rule
does (docs/design.md §3c). One rule for every tree of joints — the sensor path live and offline, and the
optical path: where the limb's bones meet the hinge axis, judged from the neighbouring joints.
"""

from __future__ import annotations

import numpy as np

from flockcal.solver.fits import TOLERANCE_M

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

# A neighbouring joint not determined yet still says where the second bone runs when the data pin its
# centre to this many times the fit's tolerance along every direction (a hinge's: along its axis). Pinned
# to two tolerances is what an avatar needs (docs/design.md §3b); it moves the hinge by about half its
# error, where a single bone keeps the whole tilt of the axis along the limb (an elbow's carrying angle:
# 14–52 mm off with one bone on the simulated bodies, docs/design.md §3c).
NEIGHBOUR_PIN = 2.0


def hinge_offsets(pairs: np.ndarray, c: np.ndarray, l: np.ndarray, axis_child: np.ndarray,
                  axis_parent: np.ndarray, hinge: np.ndarray, determined: np.ndarray,
                  ls_offset: np.ndarray | None = None, ls_error: np.ndarray | None = None,
                  centre_error: np.ndarray | None = None, tolerance: float = TOLERANCE_M,
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """How far (J,) to slide each tree joint along its own axis, by which rule (J,) it is placed, and the
    share (J,) of the data's own least-squares point in it.

    pairs (J, 2): (child, parent) sensor indices of the tree's joints; c, l (J, 3): each joint's centre in
    its child's and its parent's frame; axis_child, axis_parent (J, 3): a hinge's axis in the two frames
    (unit, the same world axis); hinge, determined (J,) bool; ls_offset, ls_error (J,): the least-squares
    point along the axis as a slide from c, and its error (`PairFits.axis_offset`, `direction_error[:, 0]`;
    NaN / inf where the axis saw no rotation beyond noise); centre_error (J,): the largest of each joint's
    `direction_error` (how closely the data pin its centre, inf: not at all); tolerance: the fit's (m).
    The new centre is c + s a_child, l + s a_parent.

    Rule (docs/design.md §3c): a hinge joins two bodies; each of them that is a limb segment (exactly two
    joints) says where its bone runs when its other joint's centre is known:
    - a *point*: a determined ball joint, or a hinge already placed by this rule. It gives the foot f of
      the perpendicular from that point onto the hinge axis (along the axis) and its distance r from it;
    - a *near point*: a ball joint the data pin to NEIGHBOUR_PIN × the tolerance along every direction
      but not yet to one, or a hinge whose own least-squares point on its axis the data pin that well.
      It serves as the second bone beside a point, never as the first (a real trial's barely moved hip
      is such a joint); alone only where nothing else will come and the data say nothing about the
      hinge's own point;
    - an *axis*: a hinge not placed yet, whose centre the data leave anywhere on its own axis. It gives
      the bone's direction only: the bone meets that axis at right angles (a wrist's or an ankle's flexion
      axis is square to the forearm or the shin), wherever this hinge's point is.
    The hinge sits where the two bones make the same angle with its axis, one on each side: with two
    points at (r₁f₀ + r₀f₁)/(r₀ + r₁), where the limb's line crosses the axis once each bone is turned
    about it into one plane, so an axis tilted along the limb (a carrying angle) cancels whatever the
    bones' lengths; with a point and an axis at the s where the bone to the point makes the angle the bone
    to the axis makes on the other side. A point alone gives its foot (the tilt stays: about the bone's
    length times it). A neighbouring hinge's *rule* point never places this one while that hinge waits on
    it: chains are placed outward from the points, so a knee over a hinged ankle is placed from the hip
    and the ankle's axis, then the ankle from the knee. A hinge with no point on either side keeps the
    minimum-norm point of its axis (the paper's "closest to the sensor origins").

    The data's own least-squares point counts for the hinge itself only in the minimum-norm fallback,
    averaged with it by weights 1/sd² (MIN_NORM_SD_M and the least-squares error): a real knee whose axis
    point the trial pins to 6 mm, with no determined neighbour, keeps its measured point. Next to the limb
    rule it does not count: along a barely turned axis under soft tissue it is off by centimetres while
    its stated error, read from a routine that repeats, says millimetres (docs/design.md §3c has the
    figures); as a neighbour's point it moves this hinge by at most about half its own error.

    Returns (s, how, share): how is 3 (a bone and the next hinge's axis), 2 or 1 (feet used), 0
    (minimum-norm) or -1 (not a hinge: s = 0).
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
    # Where each joint's centre is known well enough to say where a bone runs, at x + ref a: `known` (a
    # determined ball, a hinge this rule placed) or only `near` (pinned to NEIGHBOUR_PIN tolerances).
    pin = NEIGHBOUR_PIN * tolerance
    known = np.asarray(determined, dtype=bool) & ~hinge
    near = np.zeros(J, dtype=bool) if centre_error is None else ~hinge & (np.asarray(centre_error, dtype=float) <= pin)
    ref = np.zeros(J)
    pinned = hinge & usable & (err <= pin)
    near |= pinned
    ref[pinned] = ls[pinned]
    todo = set(np.flatnonzero(hinge).tolist())
    near_only = False  # whether a hinge with only near points may use them (once nothing else moves)
    while todo:
        now = {}
        for k in sorted(todo):
            feet, second, axes = [], [], []
            for side in (0, 1):
                others = [(o, so) for o, so in body_joints[int(P[k, side])] if o != k]
                if len(others) != 1:
                    continue  # a leaf (no bone) or a hub (no one long axis)
                o, so = others[0]
                if known[o] or near[o]:
                    d = x[o, so] + ref[o] * a[o, so] - x[k, side] if ref[o] else x[o, so] - x[k, side]
                    along = float(d @ a[k, side])
                    across = float(np.linalg.norm(d - along * a[k, side]))
                    if abs(along) * np.tan(MIN_BONE_AXIS_ANGLE) > across:
                        continue  # the bone runs too nearly along the axis to say where it meets it
                    (feet if known[o] else second).append((along, across))
                elif o in todo:
                    axes.append((x[o, so] - x[k, side], a[o, so], a[k, side]))
            if not feet:
                # Only near points: used once no known point can come any more, and only where the data say
                # nothing about the hinge's own point, which the minimum-norm fallback counts instead (a
                # real knee trial's data place its knee within 3 mm of the epicondyles along the axis, the
                # foot of a hip that barely moved 23 mm off).
                if not (near_only and second and not usable[k]):
                    continue
                feet, second = second[:1], second[1:]
            if len(feet) == 1 and second:
                feet += second
            if len(feet) == 2:
                # Each bone weighted by the other's length: the point from which both bones make the same
                # angle with the axis, so an axis tilted along the limb (a carrying angle) cancels whatever
                # the two bones' lengths; the plain mean of the feet cancels it only for equal bones.
                (f0, r0), (f1, r1) = feet
                now[k] = ((r1 * f0 + r0 * f1) / (r0 + r1), 2)
            else:
                f0, r0 = feet[0]
                facing = _facing_an_axis(f0, r0, *axes[0]) if axes else None
                now[k] = (f0, 1) if facing is None else (facing, 3)
        if not now:
            if near_only:
                break
            near_only = True
            continue
        for k, (sk, n) in now.items():  # placed together: a pass sees only the passes before it
            s[k], how[k] = sk, n
            known[k], near[k], ref[k] = True, False, sk
            todo.discard(k)
    for k in todo:  # no point on either side anywhere along its chain: the minimum-norm point of the axis line
        s[k] = blended(k, -float(x[k, 0] @ a[k, 0] + x[k, 1] @ a[k, 1]) / 2.0, MIN_NORM_SD_M)
        how[k] = 0
    return s, how, share


def _facing_an_axis(f0: float, r0: float, w: np.ndarray, a_w: np.ndarray, a_k: np.ndarray) -> float | None:
    """The slide s along the hinge axis a_k from which a bone to the next hinge's axis (through w, along
    a_w; both relative to the hinge's current point, in the same body's frame), meeting that axis at right
    angles, makes the same angle with a_k as the bone to a point with foot f0 and distance r0 does on the
    other side: (f0 − s)/r0 + g(s)/h(s) = 0, g and h the second bone's run along and across a_k. None
    when there is no such point with the second bone at least MIN_BONE_AXIS_ANGLE off the axis.

    The second bone is d(s) = Π(w − s a_k), Π the projection square to a_w: its run along a_k is
    g₀ − κs (κ = sin² of the angle between the two axes, near 0 for a wrist under an elbow), so the
    equation is linear in s once h is held; h moves with s only where the axes cross at an angle, and a
    few rounds settle it.
    """
    a_w = a_w / np.linalg.norm(a_w)
    Pw = w - (w @ a_w) * a_w
    Pa = a_k - (a_k @ a_w) * a_w
    g0, kappa = float(Pw @ a_k), float(Pa @ a_k)
    s = f0
    for _ in range(8):
        d = Pw - s * Pa
        g = float(d @ a_k)
        h = float(np.linalg.norm(d - g * a_k))
        if not h > 0:
            return None
        new = (f0 / r0 + g0 / h) / (1.0 / r0 + kappa / h)
        if abs(new - s) < 1e-9:
            s = new
            break
        s = new
    else:
        return None
    d = Pw - s * Pa
    g = float(d @ a_k)
    if abs(g) * np.tan(MIN_BONE_AXIS_ANGLE) > float(np.linalg.norm(d - g * a_k)):
        return None
    return float(s)
