"""Tracker physics and faults as pure array functions: noise, 14-bit quantisation, dropouts, slips,
hemisphere mirroring and unit-scale error. Each takes and returns arrays over (n frames, m sensors).

Randomness comes from a counter-based hash of (seed, time, sensor), not from a stream generator, so a
frame's noise depends only on its time stamp: the live performer and a recorded take agree sample by
sample, whatever batches the times arrive in.
"""

from __future__ import annotations

import numpy as np

from flockcal.rotations import as_euler, as_quat, from_euler, from_quat, from_rotvec
from flockcal.simulator.body import SimulatorError

INCH = 0.0254
# Default sensor physics (order of the paper's figures and the Flock's spec sheet):
POSITION_STD_NEAR_M = 0.002  # per axis, inside REFERENCE_RANGE_M: ~3.5 mm 3-D, the "~4 mm resolution"
REFERENCE_RANGE_M = 0.9  # noise grows with (range / this)² beyond it (the field falls off as 1/r³)
POSITION_STD_PER_SPEED_S = 0.002  # extra per-axis std per m/s of sensor speed (dynamic error)
ANGLE_STD_NEAR_RAD = np.radians(0.15)
MAX_GROWTH = 6.0  # the noise growth factor stops here (far beyond the usable range)

HEMISPHERES = {
    "forward": np.array([1.0, 0.0, 0.0]),
    "aft": np.array([-1.0, 0.0, 0.0]),
    "right": np.array([0.0, 1.0, 0.0]),
    "left": np.array([0.0, -1.0, 0.0]),
    "lower": np.array([0.0, 0.0, 1.0]),
    "upper": np.array([0.0, 0.0, -1.0]),
}

# ----------------------------------------------------------------------------------------------
# Counter-based random numbers

_M1, _M2 = np.uint64(0xBF58476D1CE4E5B9), np.uint64(0x94D049BB133111EB)
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)


def _mix(x: np.ndarray) -> np.ndarray:
    """splitmix64 finaliser on uint64 arrays (wrapping arithmetic is intended)."""
    x = x ^ (x >> np.uint64(30))
    x = x * _M1
    x = x ^ (x >> np.uint64(27))
    x = x * _M2
    return x ^ (x >> np.uint64(31))


def time_keys(times) -> np.ndarray:
    """Integer keys (n,) of time stamps, to the microsecond: the same time always draws the same noise."""
    return np.round(np.asarray(times, dtype=float) * 1e6).astype(np.int64).view(np.uint64)


def hash_uniform(seed: int, keys: np.ndarray, tail: tuple[int, ...], stream: int) -> np.ndarray:
    """Uniform numbers in (0, 1) of shape keys.shape + tail, a pure function of (seed, stream, key, index)."""
    with np.errstate(over="ignore"):
        base = _mix(np.uint64(int(seed) & 0xFFFFFFFFFFFFFFFF) ^ (np.uint64(stream + 1) * _GOLDEN))
        k = _mix(np.asarray(keys, dtype=np.uint64) + base)
        idx = np.arange(int(np.prod(tail)), dtype=np.uint64).reshape(tail)
        x = _mix(k.reshape(k.shape + (1,) * len(tail)) + (idx + np.uint64(1)) * _GOLDEN)
    return ((x >> np.uint64(11)).astype(np.float64) + 0.5) * 2.0**-53


def hash_normal(seed: int, keys: np.ndarray, tail: tuple[int, ...], stream: int) -> np.ndarray:
    """Standard normal numbers of shape keys.shape + tail (Box–Muller on two hashed uniforms)."""
    u = hash_uniform(seed, keys, tail + (2,), stream)
    return np.sqrt(-2.0 * np.log(u[..., 0])) * np.cos(2.0 * np.pi * u[..., 1])


# ----------------------------------------------------------------------------------------------
# Noise


def noise_growth(positions: np.ndarray, reference_m: float = REFERENCE_RANGE_M) -> np.ndarray:
    """Factor (n, m) by which noise grows with range from the transmitter: 1 near, (r/ref)² beyond."""
    r = np.linalg.norm(positions, axis=-1)
    return np.clip((r / reference_m) ** 2, 1.0, MAX_GROWTH)


def position_std(positions: np.ndarray, velocities: np.ndarray | None = None, scale: float = 1.0) -> np.ndarray:
    """Per-axis position noise std (n, m) in metres for sensors at `positions`, moving at `velocities`."""
    static = POSITION_STD_NEAR_M * noise_growth(positions)
    if velocities is None:
        return scale * static
    dynamic = POSITION_STD_PER_SPEED_S * np.linalg.norm(velocities, axis=-1)
    return scale * np.sqrt(static**2 + dynamic**2)


def tracker_noise(
    rotations: np.ndarray,
    positions: np.ndarray,
    times: np.ndarray,
    seed: int = 0,
    velocities: np.ndarray | None = None,
    scale: float = 1.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Add tracker-like noise: position std growing with range (and speed), small orientation jitter.

    `scale` multiplies every std (0 gives exact data back). The orientation error is a rotation about
    a random axis in the sensor frame, ~0.15° RMS per axis near the transmitter.
    """
    R = np.asarray(rotations, dtype=float)
    t = np.asarray(positions, dtype=float)
    n, m = t.shape[:2]
    keys = time_keys(times)
    sigma = position_std(t, velocities, scale)
    t_noisy = t + sigma[..., None] * hash_normal(seed, keys, (m, 3), stream=1)
    ang = scale * ANGLE_STD_NEAR_RAD * noise_growth(t)
    dR = from_rotvec(ang[..., None] * hash_normal(seed, keys, (m, 3), stream=2))
    return R @ dR, t_noisy


# ----------------------------------------------------------------------------------------------
# Quantisation to the Flock's 14-bit words (protocol.md §4)


def _words(x: np.ndarray) -> np.ndarray:
    """Values in units of 1/32768 of full scale → the 14-bit word grid (multiples of 4, clipped)."""
    return np.clip(np.round(x * 32768.0 / 4.0) * 4.0, -32768.0, 32764.0)


def quantise(
    rotations: np.ndarray,
    positions: np.ndarray,
    full_scale_in: float = 36.0,
    orientation: str = "matrix",
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Round poses to what the Flock can send: (rotations, positions, in_range (n, m)).

    Positions step FS·4/32768 inches and saturate at ±FS (in_range is False there). `orientation`
    picks the record format: "matrix" (elements step 4/32768; not re-orthonormalised, as the bird
    sends them), "angles" (Zang/Yang/Xang step 180·4/32768°) or "quaternion" (renormalised).
    """
    R = np.asarray(rotations, dtype=float)
    t = np.asarray(positions, dtype=float)
    if full_scale_in not in (36.0, 72.0, 144.0):
        raise SimulatorError(f"full scale must be 36, 72 or 144 inches, not {full_scale_in}")
    p_in = t / INCH
    in_range = np.all(np.abs(p_in) < full_scale_in, axis=-1)
    t_q = _words(p_in / full_scale_in) * full_scale_in / 32768.0 * INCH
    if orientation == "matrix":
        R_q = _words(R) / 32768.0
    elif orientation == "angles":
        angles = np.moveaxis(as_euler(R), -1, 0)
        deg = [_words(np.degrees(a) / 180.0) * 180.0 / 32768.0 for a in angles]
        R_q = from_euler(*np.radians(deg))
    elif orientation == "quaternion":
        q = _words(as_quat(R)) / 32768.0
        R_q = from_quat(q / np.linalg.norm(q, axis=-1, keepdims=True))
    else:
        raise SimulatorError(f"unknown record orientation {orientation!r}; choose matrix, angles or quaternion")
    return R_q, t_q, in_range


# ----------------------------------------------------------------------------------------------
# Dropouts, slips, hemisphere, unit scale


def dropouts(valid: np.ndarray, times: np.ndarray, prob: float, seed: int = 0, burst_s: float = 0.0) -> np.ndarray:
    """Mark sensor-frames invalid with probability `prob`; with burst_s > 0 whole bursts of that length
    go missing together (a bird that stops answering for a while). Returns a new (n, m) bool array."""
    v = np.asarray(valid, dtype=bool)
    if not 0.0 <= prob <= 1.0:
        raise SimulatorError(f"dropout probability must be within 0..1, not {prob}")
    if prob == 0.0:
        return v.copy()
    t = np.asarray(times, dtype=float)
    keys = time_keys(np.floor(t / burst_s) * burst_s) if burst_s > 0 else time_keys(t)
    lost = hash_uniform(seed, keys, (v.shape[1],), stream=3) < prob
    return v & ~lost


def slip(
    rotations: np.ndarray,
    positions: np.ndarray,
    times: np.ndarray,
    sensor: int,
    at_time: float,
    displacement: np.ndarray,
    rotation: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """A sensor sliding on the skin at `at_time`: from then on its origin is moved by `displacement`
    (metres, in its own frame before the slip) and its axes turned by `rotation` (new → old sensor
    frame). Earlier frames and other sensors are untouched. Returns new arrays."""
    R = np.array(rotations, dtype=float, copy=True)
    t = np.array(positions, dtype=float, copy=True)
    after = np.asarray(times, dtype=float) >= at_time
    if after.any():
        Ri = R[after, sensor]
        t[after, sensor] += Ri @ np.asarray(displacement, dtype=float)
        if rotation is not None:
            R[after, sensor] = Ri @ np.asarray(rotation, dtype=float)
    return R, t


def hemisphere_mask(positions: np.ndarray, hemisphere: str = "forward") -> np.ndarray:
    """(n, m) True where a sensor is outside the tracker's selected hemisphere."""
    try:
        axis = HEMISPHERES[hemisphere]
    except KeyError:
        raise SimulatorError(f"unknown hemisphere {hemisphere!r}; choose {', '.join(HEMISPHERES)}") from None
    return np.asarray(positions, dtype=float) @ axis < 0.0


def hemisphere_flips(positions: np.ndarray, hemisphere: str = "forward") -> np.ndarray:
    """What the Flock reports: the selected axis' sign is forced positive, so a sensor across the
    hemisphere boundary comes back mirrored through the transmitter (all three signs flip)."""
    p = np.asarray(positions, dtype=float)
    return np.where(hemisphere_mask(p, hemisphere)[..., None], -p, p)


def unit_scale(positions: np.ndarray, scale: float) -> np.ndarray:
    """Positions as a tracker with a unit-scale error reports them (every range times `scale`)."""
    if not 0.5 < scale < 2.0:
        raise SimulatorError(f"unit scale {scale} is implausible; a tracker's scale error is a few percent")
    return np.asarray(positions, dtype=float) * scale
