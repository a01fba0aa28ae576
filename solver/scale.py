"""Tracker unit scale (paper §4) from two sensors rigidly fixed a known distance apart.

The factor is true distance / mean measured distance: multiply a take's positions by it to put the
tracker's units right. Its spread says how well the take pinned it down. Pure numpy, no I/O.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from flockcal.errors import FlockcalError


class ScaleError(FlockcalError, ValueError):
    """A scale take that cannot give a factor (too short, sensors not rigid, a nonsense distance)."""


@dataclass(frozen=True)
class ScaleEstimate:
    """What one rigid-pair take says about the tracker's unit scale."""

    factor: float  # true / measured mean distance; corrected positions = factor * positions
    factor_stderr: float  # standard error of `factor` (batch means, so correlated noise is not hidden)
    distance_m: float  # the known true distance
    measured_mean_m: float  # mean tracker-reported distance
    measured_std_m: float  # its frame-to-frame standard deviation
    scaled_std_m: float  # std of the distance after scaling (the paper: 0.7 cm at 56.5 cm)
    frames: int  # frames used (both sensors valid)
    rotation_spread_deg: float | None  # RMS angle of the relative rotation about its mean (rigidity)

    def to_dict(self) -> dict:
        return asdict(self)


def apply_scale(positions: np.ndarray, factor: float) -> np.ndarray:
    """Positions with the unit scale applied (about the transmitter, the tracker's origin)."""
    factor = float(factor)
    if not np.isfinite(factor) or factor <= 0:
        raise ScaleError(f"scale factor must be a positive number, got {factor!r}")
    return np.asarray(positions, dtype=float) * factor


def _rotation_spread_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    """RMS angle (degrees) between each frame's relative rotation Raᵀ Rb and their chordal mean."""
    rel = np.swapaxes(Ra, -1, -2) @ Rb
    U, _, Vt = np.linalg.svd(rel.mean(axis=0))
    mean = U @ np.diag([1, 1, np.linalg.det(U @ Vt)]) @ Vt
    cos = (np.einsum("nab,ab->n", rel, mean) - 1) / 2  # trace(meanᵀ rel) = 1 + 2 cos θ
    return float(np.degrees(np.sqrt(np.mean(np.arccos(np.clip(cos, -1, 1)) ** 2))))


def rigid_pair_scale(
    positions_a: np.ndarray,
    positions_b: np.ndarray,
    distance: float,
    valid: np.ndarray | None = None,
    rotations_a: np.ndarray | None = None,
    rotations_b: np.ndarray | None = None,
    max_relative_std: float = 0.05,
    max_rotation_deg: float = 10.0,
    blocks: int = 20,
) -> ScaleEstimate:
    """Estimate the unit scale from two sensors' positions (n, 3) over a take of the rigid pair.

    `valid` (n,) selects frames where both sensors gave a record. Raises ScaleError when the distance
    varies by more than `max_relative_std` of its mean or the relative rotation by more than
    `max_rotation_deg` (the sensors are then not rigidly fixed, so no scale can be read off them).
    The standard error uses `blocks` batch means, since tracker noise is correlated from frame to frame.
    """
    distance = float(distance)
    if not np.isfinite(distance) or distance <= 0:
        raise ScaleError(f"the known distance must be a positive length in metres, got {distance!r}")
    a = np.asarray(positions_a, dtype=float)
    b = np.asarray(positions_b, dtype=float)
    keep = np.ones(len(a), dtype=bool) if valid is None else np.asarray(valid, dtype=bool)
    d = np.linalg.norm(a[keep] - b[keep], axis=1)
    n = len(d)
    if n < 10:
        raise ScaleError(f"only {n} frames with both sensors valid; record at least a few seconds of the pair")
    mean = float(d.mean())
    std = float(d.std(ddof=1))
    if mean <= 0:
        raise ScaleError("the two sensors report the same position; are they two different sensors?")
    if std > max_relative_std * mean:
        raise ScaleError(
            f"the distance between the two sensors varies by {100 * std / mean:.1f}% (std {std * 100:.2f} cm "
            f"about {mean * 100:.2f} cm); they do not look rigidly fixed — fix them to one rigid bar and record again"
        )
    spread = None
    if rotations_a is not None and rotations_b is not None:
        spread = _rotation_spread_deg(np.asarray(rotations_a)[keep], np.asarray(rotations_b)[keep])
        if spread > max_rotation_deg:
            raise ScaleError(
                f"the two sensors turn {spread:.1f}° (RMS) relative to each other; they are not rigidly fixed — "
                "fix them to one rigid bar and record again"
            )
    factor = distance / mean
    k = min(blocks, n // 10)
    if k >= 5:
        means = np.array([chunk.mean() for chunk in np.array_split(d, k)])
        mean_stderr = means.std(ddof=1) / np.sqrt(k)
    else:
        mean_stderr = std / np.sqrt(n)
    return ScaleEstimate(
        factor=float(factor),
        factor_stderr=float(factor * mean_stderr / mean),
        distance_m=distance,
        measured_mean_m=mean,
        measured_std_m=std,
        scaled_std_m=float(factor * std),
        frames=int(n),
        rotation_spread_deg=spread,
    )
