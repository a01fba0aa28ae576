"""Test oracle: the largest error the tracker's 14-bit words can put on a pose, derived here from the protocol
fact sheet (docs/protocol.md §4 "Data records and word packing") and sharing no constant or code with
flockcal.drivers, whose `quantisation_tolerance` these bounds stand beside, not on.
"""

from __future__ import annotations

import numpy as np

INCH_M = 0.0254
# A word s stands for s/32768 of its full scale, and bits 1..0 are not sent, so words are multiples of 4:
# one step is 4/32768 of full scale. The fake tracker sends the nearest step, so a value is off by at most
# half a step: 2/32768 of full scale (docs/protocol.md §4; 0.056 mm of position at 36 in).
HALF_STEP = 2.0 / 32768.0
# Stated margin: 1 % for the small-angle approximations below, 1e-12 for double rounding.
MARGIN, FLOAT = 1.01, 1e-12


def position_axis_m(full_scale_inches: float = 36.0) -> float:
    """Largest error of one position coordinate (m) at full scale 36, 72 or 144 in."""
    return MARGIN * HALF_STEP * full_scale_inches * INCH_M + FLOAT


def position_norm_m(full_scale_inches: float = 36.0) -> float:
    """Largest length (m) of a position's error vector: three coordinates, each off by half a step."""
    return np.sqrt(3.0) * position_axis_m(full_scale_inches)


def rotation_rad(orientation: str) -> float:
    """Largest rotation angle (rad) between a sent orientation and the decoded one, for a record format's
    orientation part: "angles", "matrix", "quaternion" or "" (none)."""
    if orientation == "":
        return 0.0
    if orientation == "angles":
        # Angles are s·180°/32768: each of the three is off by half a step of π rad, and a composed rotation
        # is off by at most the sum of its three angles' errors.
        bound = 3 * HALF_STEP * np.pi
    elif orientation == "matrix":
        # Nine elements s/32768, each off by half a step: ‖ΔM‖_F ≤ 3·HALF_STEP; the nearest rotation is at
        # most twice as far from the truth, and a rotation by θ moves a matrix by √2·θ (Frobenius, small θ).
        bound = 2 * 3 * HALF_STEP / np.sqrt(2.0)
    elif orientation == "quaternion":
        # Four components s/32768, each off by half a step: ‖Δq‖ ≤ 2·HALF_STEP; normalising at most doubles
        # it, and the rotation angle is twice the angle between unit quaternions.
        bound = 2 * 2 * (2 * HALF_STEP)
    else:
        raise ValueError(f"unknown orientation {orientation!r}")
    return MARGIN * bound + FLOAT


def tolerance(fmt: str, full_scale_inches: float = 36.0) -> tuple[float, float]:
    """(rotation rad, position-vector length m) for a record format named as in docs/protocol.md §4
    ("position", "angles", "matrix", "position_angles", "position_matrix", "quaternion", "position_quaternion")."""
    has_position = fmt.startswith("position")
    orientation = fmt.removeprefix("position").lstrip("_")
    return rotation_rad(orientation), position_norm_m(full_scale_inches) if has_position else 0.0
