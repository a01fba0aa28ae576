"""Test and benchmark scoring: does a slip event blame the sensor that really slipped?"""

from __future__ import annotations

import numpy as np


def attributes_slip_to(event, sensor: str, names, parent) -> bool:
    """True if `event` (a SlipEvent, or a SwapEvent read as one) blames `sensor`, or offers exactly `sensor`
    and the body it hangs on or off when that body is a leaf (a leaf's single joint cannot tell the two
    apart). `parent`: index array over `names`, −1 at the root. How tests and benchmarks score attribution."""
    if event.sensor == sensor:
        return True
    pair = set(event.candidates)
    if sensor not in pair or len(pair) != 2:
        return False
    names, parent = list(names), np.asarray(parent)
    a, b = (names.index(x) for x in pair)
    leaf = a if parent[a] == b else b if parent[b] == a else None
    return leaf is not None and not np.any(parent == leaf)
