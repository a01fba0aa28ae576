"""flockcal.rotations against scipy.spatial.transform, an implementation that shares no code with it."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from flockcal import rotations

RNG = np.random.default_rng(7)


def test_flock_angles_are_intrinsic_zyx_and_round_trip_over_leading_axes():
    angles = RNG.uniform([-np.pi, -np.pi / 2 + 1e-3, -np.pi], [np.pi, np.pi / 2 - 1e-3, np.pi], (5, 40, 3))
    R = rotations.from_euler(angles[..., 0], angles[..., 1], angles[..., 2])
    # protocol.md §5: R = Rz(A)·Ry(E)·Rx(R) is scipy's intrinsic "ZYX" sequence.
    oracle = Rotation.from_euler("ZYX", angles.reshape(-1, 3)).as_matrix().reshape(R.shape)
    assert np.abs(R - oracle).max() < 1e-14
    assert np.abs(rotations.as_euler(R) - angles).max() < 1e-12


def test_angles_at_gimbal_lock_still_give_the_same_rotation():
    R = rotations.from_euler(0.4, np.pi / 2, -0.3)
    back = rotations.as_euler(R)
    assert back[2] == 0.0  # roll folded into azimuth
    assert np.abs(rotations.from_euler(*back) - R).max() < 1e-12


def test_quaternions_are_scalar_first_with_nonnegative_w():
    R = Rotation.random(200, random_state=3)
    q = rotations.as_quat(R.as_matrix())
    xyzw = R.as_quat()
    oracle = np.concatenate([xyzw[:, 3:], xyzw[:, :3]], axis=1) * np.sign(xyzw[:, 3:])
    assert (q[:, 0] >= 0).all()
    assert np.abs(q - oracle).max() < 1e-14
    assert np.abs(rotations.from_quat(q * 3.0) - R.as_matrix()).max() < 1e-14  # any norm > 0


def test_xyzw_quaternions_are_scipys_signed_by_their_largest_component_at_every_angle():
    # Tried: random rotations, and the angles where a naive formula divides by nearly zero: half-turns about
    # each axis and about diagonals (w ≈ 0), and near-identities (x, y, z ≈ 0); over leading axes and past
    # the 1024 rows the routine keeps ready.
    half_turns = Rotation.from_rotvec(np.pi * np.array([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [0, 1, 1],
                                                          [1, 1, 1], [-1, 2, 0.5]]) /
                                      np.linalg.norm([[1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 0], [0, 1, 1],
                                                      [1, 1, 1], [-1, 2, 0.5]], axis=1)[:, None])
    small = Rotation.from_rotvec(RNG.normal(size=(20, 3)) * 1e-9)
    R = Rotation.concatenate([Rotation.random(2000, random_state=5), half_turns, small])
    oracle = R.as_quat()
    oracle *= np.sign(oracle[np.arange(len(oracle)), np.abs(oracle).argmax(axis=1)])[:, None]
    q = rotations.as_quat(R.as_matrix().reshape(-1, 1, 3, 3), scalar_first=False)
    assert q.shape == (len(oracle), 1, 4)
    q = q[:, 0]
    assert np.abs(q - oracle).max() < 1e-14
    assert (q[np.arange(len(q)), np.abs(q).argmax(axis=1)] > 0).all()
    assert np.abs(rotations.from_quat(q[:, [3, 0, 1, 2]]) - R.as_matrix()).max() < 1e-14


def test_one_routine_turns_matrices_into_quaternions():
    # Quaternions were worked out in three places (rotations, the glTF export, the live pose), two ways;
    # only flockcal.rotations may: everything else calls `as_quat`.
    import re
    from pathlib import Path

    root = Path(rotations.__file__).resolve().parent.parent
    pattern = re.compile(r"\.as_quat\(\s*\)|from_matrix\([^)]*\)\.as_quat|def \w*quaternions?\(|def (as|from)_quat\(")
    found = [f"{p.relative_to(root)}" for folder in ("flockcal", "server", "solver", "drivers", "simulator")
             for p in (root / folder).rglob("*.py") if p.name != "rotations.py" and pattern.search(p.read_text())]
    assert found == [], found


def test_the_flock_quaternion_is_that_of_the_transpose_and_conventions_are_checked():
    R = Rotation.random(50, random_state=4).as_matrix()
    q_fob = rotations.as_flock_quat(R)
    assert np.abs(rotations.from_quat(q_fob) - np.swapaxes(R, -1, -2)).max() < 1e-14
    assert np.abs(rotations.from_flock_quat(q_fob) - R).max() < 1e-14
    assert np.abs(rotations.from_flock_quat(rotations.as_flock_quat(R, "conjugate"), "conjugate") - R).max() < 1e-14
    with pytest.raises(ValueError, match="quaternion_convention must be one of"):
        rotations.as_flock_quat(R, "xyzw")  # tried: a convention name the Flock does not have


def test_rotation_vectors_match_scipy_including_tiny_angles():
    v = np.concatenate([RNG.normal(size=(100, 3)), RNG.normal(size=(20, 3)) * 1e-7, np.zeros((1, 3))])
    R = rotations.from_rotvec(v)
    assert np.abs(R - Rotation.from_rotvec(v).as_matrix()).max() < 1e-14
    big = v[:100][np.linalg.norm(v[:100], axis=1) < np.pi - 1e-6]
    assert np.abs(rotations.as_rotvec(rotations.from_rotvec(big)) - big).max() < 1e-10
    axis = np.array([0.0, 0.0, 1.0])
    assert np.abs(rotations.axis_angle(axis, np.array(0.7)) - rotations.rot_z(0.7)).max() < 1e-15


def test_skew_is_the_cross_product():
    a, b = RNG.normal(size=(2, 30, 3))
    assert np.abs(np.einsum("nij,nj->ni", rotations.skew(a), b) - np.cross(a, b)).max() < 1e-14


def test_elementary_rotations_match_scipy():
    a = RNG.uniform(-np.pi, np.pi, 10)
    for name, f in (("x", rotations.rot_x), ("y", rotations.rot_y), ("z", rotations.rot_z)):
        assert np.abs(f(a) - Rotation.from_euler(name, a[:, None]).as_matrix()).max() < 1e-15


def test_nearest_rotation_is_the_polar_factor_for_near_and_far_matrices():
    R = Rotation.random(100, random_state=5).as_matrix()
    near = R + RNG.normal(0, 1e-4, R.shape)  # a quantised tracker matrix: the Björck path
    far = R + RNG.normal(0, 0.3, R.shape)  # a mean of rotations: the SVD path
    for M in (near, far):
        U, _, Vt = np.linalg.svd(M)
        oracle = U @ np.diag([1, 1, -1]) @ Vt
        oracle = np.where((np.linalg.det(U @ Vt) > 0)[:, None, None], U @ Vt, oracle)
        assert np.abs(rotations.nearest_rotation(M) - oracle).max() < 1e-12
    reflected = R.copy()
    reflected[:, :, 2] *= -1  # det −1: the projection must still give a rotation
    assert np.allclose(np.linalg.det(rotations.nearest_rotation(reflected)), 1.0)


def test_random_rotations_are_rotations_of_the_asked_shape():
    R = rotations.random_rotations(np.random.default_rng(0), (4, 6))
    assert R.shape == (4, 6, 3, 3)
    assert np.abs(np.swapaxes(R, -1, -2) @ R - np.eye(3)).max() < 1e-14
    assert np.allclose(np.linalg.det(R), 1.0)
