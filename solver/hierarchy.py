"""A skeleton's tree checked in one place: a {child: parent} map or parent array made a parent index array,
and refused, with a message naming the problem, unless it is one rooted tree over the sensors.

`calibrate`, the service's session start (a 400 with this message) and the model a take is played
through (`reconstruct.tree_order`) all ask here.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from flockcal.solver.errors import SolverError


def sensor_index(name, names: Sequence[str], what: str, error: type[Exception] = SolverError) -> int:
    """Index of sensor `name` (a name, or an index) in `names`; `error` naming `what` and the sensors otherwise."""
    if isinstance(name, (int, np.integer)) and not isinstance(name, bool):
        if 0 <= int(name) < len(names):
            return int(name)
        raise error(f"{what}: sensor index {name} is out of range (0..{len(names) - 1})")
    try:
        return list(names).index(str(name))
    except ValueError:
        raise error(f"{what}: unknown sensor {name!r}; the sensors are: {', '.join(names)}") from None


def check_tree(parent: np.ndarray, names: Sequence[str] | None = None, what: str = "hierarchy",
               error: type[Exception] = SolverError) -> int:
    """The root of parent index array `parent` (−1 at the root); `error` unless it is one tree: no cycle, one root."""
    parent = np.asarray(parent, dtype=int)
    m = len(parent)
    label = (lambda i: names[i]) if names is not None else str  # noqa: E731
    # Walk up from every sensor at once, doubling the stride (up = the 2^k-th ancestor, −1 past a root):
    # once 2^k ≥ m only sensors on or below a cycle have not reached a root.
    up = parent.copy()
    for _ in range(max(m - 1, 1).bit_length()):
        up = np.where(up >= 0, up[np.maximum(up, 0)], up)
    cyc = np.flatnonzero(up >= 0)
    if len(cyc):
        raise error(f"{what}: {', '.join(label(i) for i in cyc)} are not connected to the root (a cycle); "
                    "a skeleton must be one tree")
    roots = np.flatnonzero(parent < 0)
    if not len(roots):
        raise error(f"{what}: no sensors")
    if len(roots) > 1:
        raise error(
            f"{what}: {len(roots)} sensors have no parent ({', '.join(label(i) for i in roots)}); "
            "give every sensor but the root a parent"
        )
    return int(roots[0])


def parse_hierarchy(hierarchy, names: Sequence[str], root=None, error: type[Exception] = SolverError) -> np.ndarray:
    """A parent index array (−1 at the root) from a {child: parent} map (names or indices, root omitted or
    mapped to None) or from a parent array; `error` naming the problem for anything that is not one tree
    over `names`, or whose root is not `root` (a name or index, when given)."""
    m = len(names)
    if isinstance(hierarchy, Mapping):
        parent = np.full(m, -1)
        explicit_roots = []
        for child, par in hierarchy.items():
            i = sensor_index(child, names, "hierarchy", error)
            if par is None or par == "":
                explicit_roots.append(names[i])
                continue
            p = sensor_index(par, names, "hierarchy", error)
            if p == i:
                raise error(f"hierarchy: {names[i]!r} is given as its own parent")
            parent[i] = p
        if len(explicit_roots) > 1:
            raise error(f"hierarchy: the root is given twice ({', '.join(explicit_roots)}); a skeleton has one root")
    else:
        parent = np.asarray(hierarchy)
        if parent.shape != (m,) or not np.issubdtype(parent.dtype, np.integer):
            raise error(f"hierarchy: a parent array must hold {m} integers, got {parent.shape} {parent.dtype}")
        parent = parent.astype(int)
        if ((parent < -1) | (parent >= m)).any() or (parent == np.arange(m)).any():
            raise error("hierarchy: parent indices must be −1 (root) or another sensor's index")
    top = check_tree(parent, names, error=error)
    if root is not None:
        r = sensor_index(root, names, "root", error)
        if r != top:
            raise error(f"root {names[r]!r} disagrees with the hierarchy, whose root is {names[top]!r}; "
                        "leave the root out or name that one")
    return parent


def check_hierarchy(hierarchy, names: Sequence[str], root=None, error: type[Exception] = SolverError) -> None:
    """`error` unless `root` (when given) is a sensor and `hierarchy` (when given) one tree over `names` rooted there."""
    if hierarchy is None:
        if root is not None:
            sensor_index(root, names, "root", error)
        return
    parse_hierarchy(hierarchy, names, root, error)
