"""The shape of a human tree for the humanoid finding (solver/humanoid.py): which bodies are hips, spine,
chest, head, arms and legs by the tree's joints alone, or why the tree is not human, in a user's words.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# What the shape test accepts, in the words every "not human" reason ends with.
HUMAN_TREE = ("a human tree is hips and chest (with or without one spine body between them), a head on the "
              "chest, two arms of three bodies on the chest and two legs of three bodies on the hips")


@dataclass(frozen=True)
class _Shape:
    """The bodies of a human tree by role (sensor indices; spine −1 when there is none)."""

    hips: int
    spine: int
    chest: int
    head: int
    arms: tuple  # two (upper, lower, hand)
    legs: tuple  # two (upper, lower, foot)


def tree_key(cal) -> frozenset:
    """The tree as the finding sees it: its joints as unordered sensor pairs, and its rigid groups."""
    pairs = cal.joints.pairs
    return frozenset([frozenset(map(int, p)) for p in pairs.tolist()]
                     + [("rigid", tuple(sorted(map(int, g)))) for g in cal.rigid_groups])


def _body_of(cal) -> np.ndarray:
    """(m,) the sensor that stands for each sensor's body: itself, or for a rigid member the member its
    group hangs from (the tree hangs rigid members from that sensor, with no joint of their own)."""
    m = len(cal.names)
    is_joint = np.zeros(m, dtype=bool)
    is_joint[cal.joints.pairs[:, 0]] = True
    rep = np.arange(m)
    for i in np.asarray(cal.order).tolist():
        p = int(cal.parent[i])
        if p >= 0 and not is_joint[i]:
            rep[i] = rep[p]
    return rep


def tree_shape(cal) -> tuple[_Shape | None, str]:
    """The roles of a human-shaped tree, or (None, why not) in a sentence for a user."""
    rep = _body_of(cal)
    bodies = sorted(set(rep.tolist()))
    nbrs: dict[int, set] = {b: set() for b in bodies}
    for c, p in cal.joints.pairs.tolist():
        a, b = int(rep[c]), int(rep[p])
        if a != b:
            nbrs[a].add(b)
            nbrs[b].add(a)
    n = len(bodies)
    if n not in (15, 16):
        what = f"{n} bodies" + (f" (of {len(rep)} sensors: some move rigidly together)" if n != len(rep) else "")
        return None, f"not a human tree: it has {what}; {HUMAN_TREE} (15 or 16 bodies)"
    branch = [b for b in bodies if len(nbrs[b]) >= 3]
    if len(branch) != 2:
        return None, (f"not a human tree: {len(branch)} bodies branch (carry three or more neighbours), a human "
                      f"tree has two, the hips and the chest; {HUMAN_TREE}")
    a, b = branch
    spine = -1
    if b not in nbrs[a]:
        between = [x for x in nbrs[a] & nbrs[b] if len(nbrs[x]) == 2]
        if len(between) != 1:
            return None, f"not a human tree: its two branching bodies are not joined through at most one body; {HUMAN_TREE}"
        spine = between[0]
    trunk = {a, b, spine}
    chains = {}
    for x in (a, b):
        out = []
        for start in sorted(nbrs[x] - trunk):
            chain, prev, cur = [start], x, start
            while len(nbrs[cur]) == 2:
                prev, cur = cur, next(iter(nbrs[cur] - {prev}))
                chain.append(cur)
            out.append(chain)
        chains[x] = out
    lengths = {x: sorted(len(c) for c in chains[x]) for x in (a, b)}
    chest = next((x for x in (a, b) if lengths[x] == [1, 3, 3]), None)
    hips = next((x for x in (a, b) if lengths[x] == [3, 3] and x != chest), None)
    if chest is None or hips is None:
        said = " and ".join(f"{'+'.join(map(str, lengths[x])) or 'nothing'}" for x in (a, b))
        return None, (f"not a human tree: its branching bodies carry chains of {said} bodies, where the chest "
                      f"carries 1+3+3 (head and arms) and the hips 3+3 (legs); {HUMAN_TREE}")
    head = next(c[0] for c in chains[chest] if len(c) == 1)
    arms = tuple(tuple(c) for c in chains[chest] if len(c) == 3)
    legs = tuple(tuple(c) for c in chains[hips])
    return _Shape(hips, spine, chest, head, arms, legs), ""
