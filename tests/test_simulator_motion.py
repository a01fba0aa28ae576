"""Promises of the motion routines (issue 3, part 2): within limits, hinge-only, smooth, seeded, loopable."""

import numpy as np
import pytest

from flockcal.simulator import body, motion
from flockcal.simulator.body import SimulatorError
from flockcal.rotations import as_rotvec

HUMAN = body.human(seed=7)


@pytest.mark.parametrize("name", motion.ROUTINES)
def test_every_joint_stays_within_its_limits(name):
    mo = motion.routine(HUMAN, name, seconds=60, rate_hz=50, seed=3)
    q = mo.coordinates(mo.times)
    lo, hi = HUMAN.limits[..., 0], HUMAN.limits[..., 1]
    assert np.all(q >= lo - 1e-12) and np.all(q <= hi + 1e-12)


def test_hinges_turn_only_about_their_axis():
    mo = motion.routine(HUMAN, "walk", seconds=20, rate_hz=50, seed=1)
    B, _ = body.bone_poses(HUMAN, mo.local_rotations, mo.root_translation)
    for name in ("l_forearm", "r_shin"):
        i = HUMAN.index(name)
        rel = np.swapaxes(B[:, HUMAN.parent[i]], 1, 2) @ B[:, i]
        rv = as_rotvec(rel)
        axis = HUMAN.hinge_axis[i]
        off_axis = rv - np.outer(rv @ axis, axis)
        assert np.abs(off_axis).max() < 1e-12
        assert np.ptp(rv @ axis) > 0.5  # and it does bend


@pytest.mark.parametrize("name", motion.ROUTINES)
def test_motion_is_twice_continuously_differentiable_including_across_the_loop(name):
    mo = motion.routine(HUMAN, name, seconds=30, rate_hz=100, seed=5)
    start = mo.period - 2.0  # the window straddles the loop boundary

    def max_jump_of_second_derivative(h):
        t = start + np.arange(int(4.0 / h)) * h
        q = mo.coordinates(t)
        _, root = mo.root_pose(t)
        x = np.concatenate([q.reshape(len(t), -1), root], axis=1)
        acc = (x[2:] - 2 * x[1:-1] + x[:-2]) / h**2
        return np.abs(np.diff(acc, axis=0)).max()

    coarse, fine = max_jump_of_second_derivative(2e-3), max_jump_of_second_derivative(1e-3)
    # A continuous second derivative changes by O(h) per step; a kink in it would not shrink with h.
    assert fine < 0.7 * coarse


def test_routines_are_deterministic_from_the_seed():
    a = motion.routine(HUMAN, "kiosk", seconds=5, rate_hz=30, seed=11)
    b = motion.routine(HUMAN, "kiosk", seconds=5, rate_hz=30, seed=11)
    c = motion.routine(HUMAN, "kiosk", seconds=5, rate_hz=30, seed=12)
    assert np.array_equal(a.local_rotations, b.local_rotations)
    assert np.array_equal(a.root_translation, b.root_translation)
    assert not np.allclose(a.local_rotations, c.local_rotations)


def test_motion_is_a_function_of_time_evaluable_anywhere_and_looping():
    mo = motion.routine(HUMAN, "walk", seconds=10, rate_hz=100, seed=2)
    t = np.array([0.0, 0.123, 7.77, 59.5, 1234.5678])
    L, r = mo.at(t)
    L2, r2 = mo.at(t + mo.period)
    assert np.allclose(L, L2, atol=1e-9) and np.allclose(r, r2, atol=1e-9)
    # Batches of any size agree with one call (the live tracker asks for a few frames at a time).
    many = np.arange(25000) / 144.0
    whole = mo.coordinates(many)
    parts = np.concatenate([mo.coordinates(many[k : k + 7]) for k in range(0, 70, 7)])
    assert np.array_equal(whole[:70], parts)
    # The sampled take is the same function at the frame times.
    assert np.allclose(mo.at(mo.times[:50])[0], mo.local_rotations[:50])


def test_walk_travels_and_turns_while_idle_barely_moves():
    walk = motion.routine(HUMAN, "walk", seconds=30, rate_hz=20, seed=1)
    idle = motion.routine(HUMAN, "idle", seconds=30, rate_hz=20, seed=1)
    path = np.linalg.norm(np.diff(walk.root_translation, axis=0), axis=1).sum()
    assert path > 1.0
    heading = walk.local_rotations[:, HUMAN.root, :2, 0]  # body forward in the horizontal plane
    assert np.ptp(np.unwrap(np.arctan2(heading[:, 1], heading[:, 0]))) > np.pi
    assert np.ptp(idle.root_translation, axis=0).max() < 0.05
    q_idle = idle.coordinates(idle.times)
    assert np.abs(q_idle - HUMAN.rest).max() < 0.1  # a sway of a few degrees at most


def test_exercise_moves_each_joint_mostly_alone():
    mo = motion.routine(HUMAN, "exercise", seconds=45, rate_hz=20, seed=1)
    q = mo.coordinates(mo.times)
    speed = np.linalg.norm(np.diff(q, axis=0), axis=2)  # (n-1, m)
    joints = [i for i in range(HUMAN.m) if HUMAN.parent[i] >= 0]
    for i in joints:
        busy = speed[:, i] > 0.5 * speed[:, i].max()
        # While joint i is busy, the joints next to it (sharing a body) are nearly still.
        neighbours = [k for k in joints if k != i and {k, HUMAN.parent[k]} & {i, HUMAN.parent[i]}]
        assert speed[busy][:, neighbours].max() < 0.3 * speed[busy, i].mean()


def test_sensors_stay_in_the_forward_hemisphere_and_the_72_inch_scale():
    limit = 72 * 0.0254
    for name in motion.ROUTINES:
        mo = motion.routine(HUMAN, name, seconds=60, rate_hz=10, seed=4)
        _, t = body.sensor_poses(HUMAN, mo)
        assert t[..., 0].min() > 0.0
        assert np.abs(t).max() < limit


@pytest.mark.parametrize(
    "kwargs",
    [
        {"name": "dance"},  # no such routine
        {"rate_hz": 500.0},  # faster than the Flock can measure
        {"rate_hz": 0.5},  # slower than 1 Hz
        {"seconds": -1.0},  # negative length
    ],
)
def test_bad_routine_requests_raise_a_simulator_error(kwargs):
    with pytest.raises(SimulatorError):
        motion.routine(HUMAN, **{"name": "walk", **kwargs})
