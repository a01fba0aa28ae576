"""Rigid-transform helpers: the nearest rotation to a tracker matrix.

Trackers report slightly non-orthonormal matrices (quantised words); the polar projection gives the closest
rotation.
"""

from __future__ import annotations

import numpy as np



def nearest_rotation(M) -> np.ndarray:
    """The rotation closest (Frobenius) to each 3×3 matrix in M (…, 3, 3): U Vᵀ of its SVD, det forced to +1."""
    M = np.asarray(M, dtype=float)
    U, _, Vt = np.linalg.svd(M)
    d = np.sign(np.linalg.det(U @ Vt))
    d = np.where(d == 0, 1.0, d)
    U = U.copy()
    U[..., :, 2] *= d[..., None]
    return U @ Vt
