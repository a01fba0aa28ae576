"""Promises of the sensor physics and faults (issue 3, part 3), each a pure array function."""

import numpy as np
import pytest

from flockcal.simulator import faults
from flockcal.simulator.body import SimulatorError
from flockcal.rotations import random_rotations

INCH = 0.0254


def _static(n, m, r):
    """n frames of m sensors parked at range r along +X, with random orientations."""
    rng = np.random.default_rng(0)
    R = np.broadcast_to(random_rotations(rng, (m,)), (n, m, 3, 3)).copy()
    t = np.zeros((n, m, 3))
    t[..., 0] = r
    return R, t, np.arange(n) / 100.0


def _angle(Ra, Rb):
    cos = (np.einsum("...ij,...ij->...", Ra, Rb) - 1.0) / 2.0
    return np.arccos(np.clip(cos, -1, 1))


def test_position_noise_is_millimetres_near_and_grows_with_range():
    R, t, times = _static(4000, 2, 0.5)
    _, near = faults.tracker_noise(R, t, times, seed=1)
    R, t, times = _static(4000, 2, 1.4)
    _, far = faults.tracker_noise(R, t, times, seed=1)
    near_3d = np.sqrt(((near - t * 0.5 / 1.4) ** 2).sum(-1).mean())
    far_3d = np.sqrt(((far - t) ** 2).sum(-1).mean())
    assert 0.002 < near_3d < 0.006  # the "~4 mm resolution" near the transmitter
    assert far_3d > 2.0 * near_3d


def test_moving_sensors_get_about_seven_millimetres_of_noise_at_range():
    R, t, times = _static(4000, 1, 1.1)
    v = np.zeros_like(t)
    v[..., 1] = 1.5  # an arm swinging at 1.5 m/s
    _, noisy = faults.tracker_noise(R, t, times, seed=2, velocities=v)
    std_3d = np.sqrt(((noisy - t) ** 2).sum(-1).mean())
    assert 0.005 < std_3d < 0.01


def test_orientation_noise_is_a_fraction_of_a_degree():
    R, t, times = _static(3000, 2, 0.6)
    Rn, _ = faults.tracker_noise(R, t, times, seed=3)
    rms = np.degrees(np.sqrt(np.mean(_angle(R, Rn) ** 2)))
    assert 0.1 < rms < 0.5
    assert np.allclose(Rn @ np.swapaxes(Rn, -1, -2), np.eye(3), atol=1e-12)  # still rotations


def test_noise_depends_only_on_the_time_stamp_and_seed():
    R, t, times = _static(50, 3, 0.8)
    _, a = faults.tracker_noise(R, t, times, seed=4)
    _, b = faults.tracker_noise(R[10:20], t[10:20], times[10:20], seed=4)
    _, c = faults.tracker_noise(R, t, times, seed=5)
    assert np.array_equal(a[10:20], b)
    assert not np.allclose(a, c)
    # Independent across sensors and frames: no two sensors share a draw.
    d = (a - t)[..., 1]
    assert abs(np.corrcoef(d[:, 0], d[:, 1])[0, 1]) < 0.5


@pytest.mark.parametrize("fs", [36.0, 72.0, 144.0])
def test_positions_are_quantised_to_the_14_bit_word_and_saturate_at_full_scale(fs):
    rng = np.random.default_rng(6)
    t = rng.uniform(-1.0, 1.0, (200, 4, 3)) * fs * INCH * 1.1
    R = random_rotations(rng, (200, 4))
    _, tq, ok = faults.quantise(R, t, full_scale_in=fs)
    step = fs * 4 / 32768 * INCH
    words = tq / step
    assert np.allclose(words, np.round(words), atol=1e-9)
    inside = np.all(np.abs(t) < fs * INCH, axis=-1)
    assert np.array_equal(ok, inside)
    assert np.abs(tq - t)[inside].max() <= step / 2 + 1e-12
    assert np.abs(tq).max() <= fs * INCH  # saturated, never beyond the word range


def test_orientation_quantisation_matches_each_record_format():
    rng = np.random.default_rng(7)
    R = random_rotations(rng, (500, 2))
    t = np.zeros((500, 2, 3))
    Rm, _, _ = faults.quantise(R, t, orientation="matrix")
    assert np.allclose(Rm * 8192, np.round(Rm * 8192))  # multiples of 4/32768
    below_top = R < 32764 / 32768  # +1.0 has no word: it saturates at 0x7FFC
    assert np.abs(Rm - R)[below_top].max() <= 2 / 32768 + 1e-15
    assert np.abs(Rm - R).max() <= 4 / 32768 + 1e-15
    Ra, _, _ = faults.quantise(R, t, orientation="angles")
    assert np.degrees(_angle(R, Ra)).max() < 2 * 180 * 4 / 32768 + 1e-6  # within about one angle step
    Rq, _, _ = faults.quantise(R, t, orientation="quaternion")
    assert np.degrees(_angle(R, Rq)).max() < 0.05
    assert np.allclose(Rq @ np.swapaxes(Rq, -1, -2), np.eye(3), atol=1e-12)


def test_dropouts_lose_the_asked_fraction_and_can_come_in_bursts():
    times = np.arange(20000) / 100.0
    v = faults.dropouts(np.ones((20000, 4), bool), times, prob=0.05, seed=1)
    assert 0.04 < 1 - v.mean() < 0.06
    burst = faults.dropouts(np.ones((20000, 4), bool), times, prob=0.05, seed=1, burst_s=0.2)
    assert 0.03 < 1 - burst.mean() < 0.07
    runs = np.diff(np.flatnonzero(np.diff(burst[:, 0].astype(int)))).min()
    assert runs >= 19  # nothing shorter than a 0.2 s burst at 100 Hz
    assert faults.dropouts(np.ones((10, 2), bool), times[:10], prob=0.0).all()


def test_slip_moves_only_that_sensor_from_the_slip_time_on():
    R, t, times = _static(100, 3, 0.7)
    d = np.array([0.02, 0.0, 0.0])
    R2, t2 = faults.slip(R, t, times, sensor=1, at_time=0.5, displacement=d, rotation=np.eye(3))
    after = times >= 0.5
    assert np.array_equal(t2[~after], t[~after]) and np.array_equal(t2[:, [0, 2]], t[:, [0, 2]])
    jump = np.linalg.norm(t2[after, 1] - t[after, 1], axis=-1)
    assert np.allclose(jump, 0.02)
    # The displacement is in the sensor's own frame: it moves along the sensor's x axis.
    assert np.allclose(t2[after, 1] - t[after, 1], 0.02 * R[after, 1, :, 0])


def test_hemisphere_mirrors_sensors_on_the_wrong_side_through_the_transmitter():
    p = np.array([[[0.5, 0.2, -0.3], [-0.4, 0.1, 0.2]]])
    f = faults.hemisphere_flips(p, "forward")
    assert np.array_equal(f[0, 0], p[0, 0])
    assert np.array_equal(f[0, 1], -p[0, 1])  # X forced positive, the other two signs flip
    assert faults.hemisphere_flips(p, "lower")[0, 0, 2] == 0.3


def test_unit_scale_error_stretches_every_range():
    p = np.array([[[0.5, 0.2, -0.3], [0.1, 0.1, 0.2]]])
    s = faults.unit_scale(p, 1.02)
    assert np.allclose(np.linalg.norm(s[0, 0] - s[0, 1]), 1.02 * np.linalg.norm(p[0, 0] - p[0, 1]))


@pytest.mark.parametrize(
    "call",
    [
        lambda: faults.quantise(np.eye(3)[None, None], np.zeros((1, 1, 3)), full_scale_in=48.0),  # no 48-inch scale
        lambda: faults.quantise(np.eye(3)[None, None], np.zeros((1, 1, 3)), orientation="euler"),  # unknown format
        lambda: faults.dropouts(np.ones((2, 2), bool), np.arange(2.0), prob=1.5),  # probability above 1
        lambda: faults.hemisphere_flips(np.zeros((1, 1, 3)), "up"),  # not a Flock hemisphere name
        lambda: faults.unit_scale(np.zeros(3), 25.4),  # inches-to-mm mistaken for a scale error
    ],
)
def test_bad_fault_parameters_raise_a_simulator_error(call):
    with pytest.raises(SimulatorError):
        call()
