"""Small vectorised rotation helpers for the simulator (rotation vectors, Euler angles, random rotations).

Everything broadcasts over leading axes; matrices map body-frame column vectors into the outer frame.
Kept exact to machine precision, because the solver is checked against these poses to 1e-9 m.
"""

from __future__ import annotations

import numpy as np

# Quaternions (w, x, y, z) → matrices: the codec's conversion, so the simulator and the wire agree.
from flockcal.drivers.codec import quaternion_to_rotation as quat_to_matrix


def hat(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices (..., 3, 3) of vectors (..., 3)."""
    v = np.asarray(v, dtype=float)
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def rotvec_to_matrix(q: np.ndarray) -> np.ndarray:
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


def axis_angle(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rotations (..., 3, 3) by `angle` (...) about unit `axis` (..., 3)."""
    axis = np.asarray(axis, dtype=float)
    return rotvec_to_matrix(axis * np.asarray(angle, dtype=float)[..., None])


def matrix_to_rotvec(R: np.ndarray) -> np.ndarray:
    """Rotation vectors (..., 3) of rotation matrices (..., 3, 3) (angles in [0, π])."""
    from scipy.spatial.transform import Rotation

    R = np.asarray(R, dtype=float)
    flat = R.reshape(-1, 3, 3)
    return Rotation.from_matrix(flat).as_rotvec().reshape(R.shape[:-2] + (3,))


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
    return _elementary(a, 1, 2)


def rot_y(a) -> np.ndarray:
    return _elementary(a, 2, 0)


def rot_z(a) -> np.ndarray:
    return _elementary(a, 0, 1)


def euler_zyx_to_matrix(azimuth, elevation, roll) -> np.ndarray:
    """R = Rz(A)·Ry(E)·Rx(R): the Flock's angle convention (fob-protocol.md §5), sensor → transmitter."""
    A, E, Rr = (np.asarray(x, dtype=float) for x in (azimuth, elevation, roll))
    cA, sA, cE, sE, cR, sR = np.cos(A), np.sin(A), np.cos(E), np.sin(E), np.cos(Rr), np.sin(Rr)
    out = np.empty(np.broadcast(A, E, Rr).shape + (3, 3))
    out[..., 0, 0] = cE * cA
    out[..., 0, 1] = -cR * sA + sR * sE * cA
    out[..., 0, 2] = sR * sA + cR * sE * cA
    out[..., 1, 0] = cE * sA
    out[..., 1, 1] = cR * cA + sR * sE * sA
    out[..., 1, 2] = -sR * cA + cR * sE * sA
    out[..., 2, 0] = -sE
    out[..., 2, 1] = sR * cE
    out[..., 2, 2] = cR * cE
    return out


def matrix_to_euler_zyx(R: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(azimuth, elevation, roll) in radians with R = Rz(A)·Ry(E)·Rx(R); elevation in [−π/2, π/2]."""
    R = np.asarray(R, dtype=float)
    A = np.arctan2(R[..., 1, 0], R[..., 0, 0])
    E = np.arcsin(np.clip(-R[..., 2, 0], -1.0, 1.0))
    Rr = np.arctan2(R[..., 2, 1], R[..., 2, 2])
    return A, E, Rr


def random_rotations(rng: np.random.Generator, shape: tuple[int, ...] = ()) -> np.ndarray:
    """Uniformly distributed rotations (shape + (3, 3)) from unit quaternions."""
    q = rng.normal(size=shape + (4,))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    return quat_to_matrix(q)


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """Unit quaternions (..., 4) (w, x, y, z), w ≥ 0, of rotation matrices (..., 3, 3)."""
    from scipy.spatial.transform import Rotation

    R = np.asarray(R, dtype=float)
    xyzw = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_quat()
    wxyz = np.concatenate([xyzw[:, 3:], xyzw[:, :3]], axis=1)
    wxyz *= np.where(wxyz[:, :1] < 0, -1.0, 1.0)
    return wxyz.reshape(R.shape[:-2] + (4,))
