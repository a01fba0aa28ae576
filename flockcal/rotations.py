"""Rotation maths for every layer, with the Flock of Birds' conventions written once (protocol.md §5).

Rotations are (..., 3, 3) matrices mapping body-frame column vectors into the outer frame; every function
broadcasts over leading axes. Names follow scipy.spatial.transform: `from_x` builds matrices from x,
`as_x` gives x of matrices. Quaternions are scalar first (w, x, y, z), as the Flock sends them.
"""

from __future__ import annotations

import numpy as np

# How the Flock's quaternion relates to R (sensor → transmitter): "fob" is the quaternion of M = Rᵀ, the
# matrix the bird sends (protocol.md §5); "conjugate" is R's own, for a bird found to send that (the
# manual's convention is unconfirmed on hardware).
QUATERNION_CONVENTIONS = ("fob", "conjugate")

_I3 = np.eye(3)
_CONJUGATE = np.array([1.0, -1.0, -1.0, -1.0])


# -- the Flock's angles: R = Rz(A)·Ry(E)·Rx(R), sensor → transmitter -------------------------------------


def from_euler(azimuth, elevation, roll) -> np.ndarray:
    """R = Rz(A)·Ry(E)·Rx(R) (sensor → transmitter) from angles in radians, shape (..., 3, 3)."""
    a, e, r = (np.asarray(x, dtype=float) for x in (azimuth, elevation, roll))
    ca, sa, ce, se, cr, sr = np.cos(a), np.sin(a), np.cos(e), np.sin(e), np.cos(r), np.sin(r)
    out = np.empty(np.broadcast(a, e, r).shape + (3, 3))
    out[..., 0, 0] = ca * ce
    out[..., 0, 1] = ca * se * sr - sa * cr
    out[..., 0, 2] = ca * se * cr + sa * sr
    out[..., 1, 0] = sa * ce
    out[..., 1, 1] = sa * se * sr + ca * cr
    out[..., 1, 2] = sa * se * cr - ca * sr
    out[..., 2, 0] = -se
    out[..., 2, 1] = ce * sr
    out[..., 2, 2] = ce * cr
    return out


def as_euler(rot: np.ndarray) -> np.ndarray:
    """(..., 3) angles (A, E, R) in radians of (..., 3, 3) rotations; at elevation ±90° roll is set to 0."""
    rot = np.asarray(rot, dtype=float)
    ce = np.hypot(rot[..., 0, 0], rot[..., 1, 0])
    e = np.arctan2(-rot[..., 2, 0], ce)
    a = np.arctan2(rot[..., 1, 0], rot[..., 0, 0])
    r = np.arctan2(rot[..., 2, 1], rot[..., 2, 2])
    # Gimbal lock: A and R are no longer separable; fold everything into A so that the
    # composed rotation stays right (R01 = -sin A, R11 = cos A when roll = 0).
    lock = ce < 1e-7
    if np.any(lock):
        a = np.where(lock, np.arctan2(-rot[..., 0, 1], rot[..., 1, 1]), a)
        r = np.where(lock, 0.0, r)
    return np.stack([a, e, r], axis=-1)


# -- quaternions ---------------------------------------------------------------------------------------


def from_quat(q: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotations of (..., 4) scalar-first quaternions (any norm > 0)."""
    q = np.asarray(q, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    out = np.empty(q.shape[:-1] + (3, 3))
    out[..., 0, 0] = 1 - 2 * (y * y + z * z)
    out[..., 0, 1] = 2 * (x * y - z * w)
    out[..., 0, 2] = 2 * (x * z + y * w)
    out[..., 1, 0] = 2 * (x * y + z * w)
    out[..., 1, 1] = 1 - 2 * (x * x + z * z)
    out[..., 1, 2] = 2 * (y * z - x * w)
    out[..., 2, 0] = 2 * (x * z - y * w)
    out[..., 2, 1] = 2 * (y * z + x * w)
    out[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return out


def as_quat(rot: np.ndarray, scalar_first: bool = True) -> np.ndarray:
    """(..., 4) unit quaternions of (..., 3, 3) rotations: the one routine every layer uses.

    `scalar_first` (the Flock's order, the default): (w, x, y, z) with w ≥ 0. Otherwise (x, y, z, w), the
    order of scipy, glTF, VRPN and VMC, signed as Shepperd's rule gives it: its largest component positive
    (what scipy's `Rotation.from_matrix(R).as_quat()` returns). Each matrix takes the form of the rule that
    divides by its largest component (numerically safe at every angle), and all four forms come out of one
    product with `_FORMS`: 23 µs for the 16 matrices of a live frame where scipy takes 175 µs, and faster
    at any count (benchmarks/bench_pose_rig.py times the live pose that calls it up to 144 times a second).
    """
    rot = np.asarray(rot, dtype=float)
    R = rot.reshape(-1, 9)
    # In place and through views (each form's own component is every fifth of its 16): the streams call this
    # up to 144 times a second on a few dozen matrices, where each numpy call's overhead is the cost.
    forms = R @ _FORMS_R
    forms += _FORMS_1
    rows = _ROWS[:len(R)] if len(R) <= len(_ROWS) else np.arange(len(R))
    q = forms.reshape(-1, 4, 4)[rows, forms[:, ::5].argmax(axis=1)]
    norm = np.einsum("ij,ij->i", q, q)
    q /= np.sqrt(norm, out=norm)[:, None]
    if scalar_first:
        q = q[:, [3, 0, 1, 2]]
        q *= np.where(q[:, :1] < 0, -1.0, 1.0)
    return q.reshape(rot.shape[:-2] + (4,))


# Shepperd's four forms of a rotation's quaternion (x, y, z, w), each 4× the quaternion times one of its
# components, as weights on (1, r00, r01, r02, r10, r11, r12, r20, r21, r22): row 4i + c is form i's
# component c. Form i is the one whose own component i (4 q_i² > 0) is largest: forms x, y, z, w.
_FORMS = np.array([
    # form x: 1 + r00 − r11 − r22, r01 + r10, r02 + r20, r21 − r12
    [1, 1, 0, 0, 0, -1, 0, 0, 0, -1], [0, 0, 1, 0, 1, 0, 0, 0, 0, 0], [0, 0, 0, 1, 0, 0, 0, 1, 0, 0],
    [0, 0, 0, 0, 0, 0, -1, 0, 1, 0],
    # form y: r01 + r10, 1 − r00 + r11 − r22, r12 + r21, r02 − r20
    [0, 0, 1, 0, 1, 0, 0, 0, 0, 0], [1, -1, 0, 0, 0, 1, 0, 0, 0, -1], [0, 0, 0, 0, 0, 0, 1, 0, 1, 0],
    [0, 0, 0, 1, 0, 0, 0, -1, 0, 0],
    # form z: r02 + r20, r12 + r21, 1 − r00 − r11 + r22, r10 − r01
    [0, 0, 0, 1, 0, 0, 0, 1, 0, 0], [0, 0, 0, 0, 0, 0, 1, 0, 1, 0], [1, -1, 0, 0, 0, -1, 0, 0, 0, 1],
    [0, 0, -1, 0, 1, 0, 0, 0, 0, 0],
    # form w: r21 − r12, r02 − r20, r10 − r01, 1 + r00 + r11 + r22
    [0, 0, 0, 0, 0, 0, -1, 0, 1, 0], [0, 0, 0, 1, 0, 0, 0, -1, 0, 0], [0, 0, -1, 0, 1, 0, 0, 0, 0, 0],
    [1, 1, 0, 0, 0, 1, 0, 0, 0, 1],
], dtype=float).T
_FORMS_1, _FORMS_R = _FORMS[0], _FORMS[1:]  # the constant, then the weights on R's entries (the same layout as ever)
_ROWS = np.arange(1024)  # row numbers made once: a live frame's matrices are a few dozen


def _check_convention(convention: str) -> None:
    if convention not in QUATERNION_CONVENTIONS:
        raise ValueError(f"quaternion_convention must be one of {QUATERNION_CONVENTIONS}, not {convention!r}")


def as_flock_quat(rot: np.ndarray, convention: str = "fob") -> np.ndarray:
    """The quaternion a bird sends for rotations R (sensor → transmitter) under `convention`."""
    _check_convention(convention)
    q = as_quat(rot)
    if convention == "fob":
        q[..., 1:] *= -1.0  # quaternion of M = Rᵀ
    return q


def from_flock_quat(q: np.ndarray, convention: str = "fob") -> np.ndarray:
    """Rotations R (sensor → transmitter) of the quaternions a bird sent under `convention`."""
    _check_convention(convention)
    q = np.asarray(q, dtype=float)
    if convention == "fob":
        q = q * _CONJUGATE
    return from_quat(q)


# -- rotation vectors, axes and angles -----------------------------------------------------------------


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices (..., 3, 3) of vectors (..., 3): skew(v) @ u = v × u."""
    v = np.asarray(v, dtype=float)
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def from_rotvec(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) from rotation vectors (..., 3) (Rodrigues, stable near zero)."""
    q = np.asarray(q, dtype=float)
    theta2 = np.einsum("...i,...i->...", q, q)
    theta = np.sqrt(theta2)
    small = theta < 1e-4
    safe = np.where(small, 1.0, theta)
    # Taylor series below 1e-4 rad keep full precision where sin(θ)/θ would cancel.
    a = np.where(small, 1.0 - theta2 / 6.0 + theta2**2 / 120.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - theta2 / 24.0 + theta2**2 / 720.0, (1.0 - np.cos(safe)) / safe**2)
    # R = I + a K + b K² with K² = q qᵀ − θ² I, written out: no 3×3 products per rotation.
    out = (b[..., None, None] * q[..., :, None]) * q[..., None, :]
    diag = 1.0 - b * theta2
    x, y, z = a * q[..., 0], a * q[..., 1], a * q[..., 2]
    out[..., 0, 0] += diag
    out[..., 1, 1] += diag
    out[..., 2, 2] += diag
    out[..., 0, 1] -= z
    out[..., 1, 0] += z
    out[..., 0, 2] += y
    out[..., 2, 0] -= y
    out[..., 1, 2] -= x
    out[..., 2, 1] += x
    return out


def as_rotvec(rot: np.ndarray) -> np.ndarray:
    """Rotation vectors (..., 3) of rotation matrices (..., 3, 3) (angles in [0, π])."""
    from scipy.spatial.transform import Rotation

    rot = np.asarray(rot, dtype=float)
    return Rotation.from_matrix(rot.reshape(-1, 3, 3)).as_rotvec().reshape(rot.shape[:-2] + (3,))


def axis_angle(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rotations (..., 3, 3) by `angle` (...) about unit `axis` (..., 3)."""
    axis = np.asarray(axis, dtype=float)
    return from_rotvec(axis * np.asarray(angle, dtype=float)[..., None])


def _elementary(a, i: int, j: int) -> np.ndarray:
    """Rotations by angles `a` in the (i, j) coordinate plane (right-handed about the third axis)."""
    a = np.asarray(a, dtype=float)
    c, s = np.cos(a), np.sin(a)
    out = np.zeros(a.shape + (3, 3))
    out[..., 3 - i - j, 3 - i - j] = 1.0
    out[..., i, i], out[..., j, j] = c, c
    out[..., i, j], out[..., j, i] = -s, s
    return out


def rot_x(a) -> np.ndarray:
    """Rotations (..., 3, 3) by angles `a` about x."""
    return _elementary(a, 1, 2)


def rot_y(a) -> np.ndarray:
    """Rotations (..., 3, 3) by angles `a` about y."""
    return _elementary(a, 2, 0)


def rot_z(a) -> np.ndarray:
    """Rotations (..., 3, 3) by angles `a` about z."""
    return _elementary(a, 0, 1)


def random_rotations(rng: np.random.Generator, shape: tuple[int, ...] = ()) -> np.ndarray:
    """Uniformly distributed rotations (shape + (3, 3)) from normalised Gaussian quaternions."""
    q = rng.normal(size=shape + (4,))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    return from_quat(q)


# -- projection onto SO(3) -----------------------------------------------------------------------------


def nearest_rotation(m: np.ndarray) -> np.ndarray:
    """The rotation closest (Frobenius) to each (..., 3, 3) matrix: the polar factor, det +1.

    Nearly orthonormal input (a quantised tracker matrix) takes three Björck iterations, which
    converge quadratically; anything far from a rotation goes through the SVD (U Vᵀ, det forced to +1).
    """
    m = np.asarray(m, dtype=float)
    r = m
    for _ in range(3):
        r = r @ (1.5 * _I3 - 0.5 * np.swapaxes(r, -1, -2) @ r)
    err = np.abs(np.swapaxes(r, -1, -2) @ r - _I3).max(axis=(-2, -1))
    bad = ~(err < 1e-12) | (_det3(r) < 0)
    if np.any(bad):
        r[bad] = _svd_projection(m[bad])
    return r


def _svd_projection(m: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(m)
    d = np.sign(np.linalg.det(U @ Vt))
    d = np.where(d == 0, 1.0, d)
    U = U.copy()
    U[..., :, 2] *= d[..., None]
    return U @ Vt


def _det3(r: np.ndarray) -> np.ndarray:
    """Determinants of (..., 3, 3) matrices, written out (np.linalg.det costs more than this for a few)."""
    return (r[..., 0, 0] * (r[..., 1, 1] * r[..., 2, 2] - r[..., 1, 2] * r[..., 2, 1])
            - r[..., 0, 1] * (r[..., 1, 0] * r[..., 2, 2] - r[..., 1, 2] * r[..., 2, 0])
            + r[..., 0, 2] * (r[..., 1, 0] * r[..., 2, 1] - r[..., 1, 1] * r[..., 2, 0]))
