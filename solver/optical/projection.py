"""Skeleton projection (Kirk et al. 2005 §4): per body, align every frame's markers and joint points to
a reference with the best rigid transform and average, giving fixed marker offsets and joint positions
in the body's own frame, hence bone lengths that do not wobble from frame to frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations

import numpy as np

from flockcal.solver.optical.rigid import nanmean, procrustes_mean, to_body


@dataclass(frozen=True)
class BodyShape:
    markers: np.ndarray  # (q,) marker indices on this body
    joints: list[int]  # joint ids (= child group) touching this body: inboard first when it has one
    marker_offsets: np.ndarray  # (q, 3) body frame
    joint_offsets: np.ndarray  # (len(joints), 3) body frame
    frame_ok: np.ndarray  # frames (of those the offsets were averaged over) where the body's pose is determined


def body_points(markers: np.ndarray, group: np.ndarray, joint_points: dict[int, np.ndarray], joints: list[int]):
    """(n, q + j, 3) the body's markers followed by the per-frame points of its joints."""
    extra = [joint_points[j][:, None, :] for j in joints]
    return np.concatenate([markers[:, group]] + extra, axis=1) if extra else markers[:, group]


# Frames a body's fixed offsets are averaged over at most (evenly spread): they are means, and 1000 frames
# hold them to a small fraction of a millimetre while a 30 s take at 144 Hz has 4320.
SHAPE_FRAMES = 1000


def project_body(markers: np.ndarray, group: np.ndarray, joint_points: dict[int, np.ndarray], joints: list[int]) -> BodyShape:
    """Fixed offsets of one body's markers and joints.

    A body with three or more markers is aligned on its markers alone (per-frame joint points are
    noisier); with one or two markers its joint points are needed to pin the rotation too.
    """
    n = len(markers)
    if n > SHAPE_FRAMES:
        pick = np.linspace(0, n - 1, SHAPE_FRAMES).round().astype(int)
        markers = markers[pick]
        joint_points = {j: joint_points[j][pick] for j in joints}
    pts = body_points(markers, group, joint_points, joints)
    q = len(group)
    align = pts if q < 3 else pts[:, :q]
    shape, R, t, ok = procrustes_mean(align)
    local = to_body(R[ok], t[ok], pts[ok])
    mean = nanmean(local, axis=0)
    # Re-centre on the markers' centroid so the body frame does not depend on which points aligned it.
    mean = mean - nanmean(mean[:q], axis=0)
    return BodyShape(group, list(joints), mean[:q], mean[q:], ok)


def skeleton_shapes(markers, groups, parent, joint_points, skip=(), only=None, previous=None) -> list[BodyShape]:
    """BodyShape per group; joint j (j's inboard joint) touches groups j and parent[j]. Joints in
    `skip` are left out (added later by the rigid-transform route). With `only` (bodies) and `previous`
    (shapes), the other bodies keep their previous shape."""
    shapes = []
    for g, group in enumerate(groups):
        if only is not None and previous is not None and g not in only:
            shapes.append(previous[g])
            continue
        joints = ([g] if parent[g] >= 0 else []) + [int(c) for c in np.flatnonzero(parent == g)]
        joints = [j for j in joints if j not in skip]
        shapes.append(project_body(markers, group, joint_points, joints))
    return shapes


def bone_lengths(shapes: list[BodyShape], parent: np.ndarray) -> list[tuple[int, int | None, int, float]]:
    """(body, from_joint | None, to_joint, length) in docs/design.md §5's sense: inboard → each outboard
    joint; for the root, between each pair of its outboard joints (from_joint the first)."""
    out = []
    for g, s in enumerate(shapes):
        pos = dict(zip(s.joints, s.joint_offsets))
        kids = [j for j in s.joints if j != g]
        if parent[g] >= 0:
            for k in kids:
                out.append((g, g, k, float(np.linalg.norm(pos[k] - pos[g]))))
        else:
            for a, b in combinations(kids, 2):
                out.append((g, a, b, float(np.linalg.norm(pos[a] - pos[b]))))
    return out
