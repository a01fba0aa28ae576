"""Hemispheres: which half of space around the transmitter a bird reports, and the mirror it applies (protocol.md §9).
"""

from __future__ import annotations

import numpy as np

from flockcal.drivers.commands import Command, fbb_prefix


HEMISPHERES: dict[str, tuple[int, int]] = {
    "forward": (0x00, 0x00), "aft": (0x00, 0x01), "upper": (0x0C, 0x01),
    "lower": (0x0C, 0x00), "left": (0x06, 0x01), "right": (0x06, 0x00),
}
HEMISPHERE_BY_BYTES = {v: k for k, v in HEMISPHERES.items()}
_HEMISPHERE_AXIS = {0x00: 0, 0x06: 1, 0x0C: 2}


def hemisphere_bytes(name: str) -> bytes:
    """The two data bytes (axis, sign) of HEMISPHERE 'L' or CHANGE p22."""
    return bytes(HEMISPHERES[name])


def hemisphere_command(name: str, address: int = 0, addressing: str = "normal") -> bytes:
    return fbb_prefix(address, addressing) + bytes([Command.HEMISPHERE]) + hemisphere_bytes(name)


def hemisphere_vector(name: str) -> np.ndarray:
    """Unit vector of the hemisphere's direction in transmitter axes (forward = +X, lower = +Z)."""
    axis, sign = HEMISPHERES[name]
    v = np.zeros(3)
    v[_HEMISPHERE_AXIS[axis]] = -1.0 if sign else 1.0
    return v


def fold_to_hemisphere(positions: np.ndarray, name: str) -> np.ndarray:
    """What the bird reports: positions outside the hemisphere come back mirrored (p → −p)."""
    positions = np.asarray(positions, dtype=float)
    flip = positions @ hemisphere_vector(name) < 0
    return np.where(flip[..., None], -positions, positions)
