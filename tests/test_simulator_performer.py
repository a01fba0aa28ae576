"""Promises of the live performer (the fake tracker's pose source) and of take.simulate."""

import threading

import numpy as np
import pytest

from flockcal.simulator.body import SimulatorError, sensor_poses
from flockcal.simulator.performer import Performer
from flockcal.simulator.take import simulate


def _joint_gap(perf, times, at_time):
    """Largest distance between each joint as seen from its two sensors, using truth at `at_time`."""
    R, t = perf.exact_poses(times)
    truth = perf.truth(at_time)
    gaps = {}
    for j in truth["joints"]:
        i, p = perf.model.index(j["child"]), perf.model.index(j["parent"])
        a = np.einsum("nij,j->ni", R[:, i], j["c"]) + t[:, i]
        b = np.einsum("nij,j->ni", R[:, p], j["l"]) + t[:, p]
        gaps[j["child"]] = np.linalg.norm(a - b, axis=1).max()
    return gaps


def test_poses_are_si_transmitter_frame_arrays_and_deterministic_for_given_times():
    perf = Performer(routine="walk", seed=3)
    times = np.arange(200) / 144.0
    R, t, valid = perf.poses(times)
    assert perf.n_sensors == 16 and len(perf.names) == 16
    assert R.shape == (200, 16, 3, 3) and t.shape == (200, 16, 3) and valid.shape == (200, 16)
    assert np.allclose(R @ np.swapaxes(R, -1, -2), np.eye(3), atol=1e-9)
    assert 0.2 < np.linalg.norm(t, axis=-1).mean() < 2.0  # metres from the transmitter
    # The same times in other batches, or asked again, give the same numbers (noise included).
    R2, t2, v2 = Performer(routine="walk", seed=3).poses(times[50:60])
    assert np.array_equal(t2, t[50:60]) and np.array_equal(R2, R[50:60]) and np.array_equal(v2, valid[50:60])


def test_exact_performer_matches_the_body_model_forward_kinematics():
    # Rigidly mounted sensors (no soft tissue): then the poses are the body model's kinematics exactly.
    perf = Performer(routine="kiosk", seed=1, noise=None, sta_mm=0)
    times = np.arange(100) / 50.0
    R, t, _ = perf.poses(times)
    L, root = perf.motion.at(times)
    R2, t2 = sensor_poses(perf.model, L, root)
    assert np.array_equal(R, R2) and np.array_equal(t, t2)


def test_inject_slip_moves_one_sensor_from_then_on_and_truth_follows():
    # Without soft tissue, so that the truth's placements fit every frame exactly (to 1e-12 m).
    perf = Performer(routine="exercise", seed=2, noise=None, sta_mm=0)
    before = np.arange(0, 100) / 100.0
    R0, t0, _ = perf.poses(before)
    ev = perf.inject_slip("l_forearm", 0.02, at_time=1.5)
    assert perf.model.names[ev.sensor] == "l_forearm" and ev.time_s == 1.5
    assert np.linalg.norm(ev.displacement_m) == pytest.approx(0.02)
    times = np.arange(0, 300) / 100.0
    exact_R, exact_t, _ = Performer(routine="exercise", seed=2, noise=None, sta_mm=0).poses(times)
    R, t, _ = perf.poses(times)
    i = perf.model.index("l_forearm")
    after = times >= 1.5
    assert np.array_equal(t[~after], exact_t[~after])
    assert np.allclose(np.linalg.norm(t[after, i] - exact_t[after, i], axis=1), 0.02)
    others = np.arange(perf.n_sensors) != i
    assert np.array_equal(t[:, others], exact_t[:, others])
    # Truth before the slip fits the early frames; truth after it fits the late ones, exactly.
    assert max(_joint_gap(perf, times[~after], at_time=0.0).values()) < 1e-12
    assert max(_joint_gap(perf, times[after], at_time=2.0).values()) < 1e-12
    stale = _joint_gap(perf, times[after], at_time=0.0)
    assert stale["l_forearm"] > 0.01 and stale["l_hand"] > 0.01  # its own joint and its child's
    assert stale["l_upper_arm"] < 1e-12 and stale["r_forearm"] < 1e-12
    assert perf.truth()["slip_events"][0]["joints"] == ["l_forearm", "l_hand"]


def test_a_slip_without_a_time_starts_after_the_last_frame_streamed():
    perf = Performer(routine="walk", seed=1, noise=None)
    streamed = np.arange(100) / 100.0
    R, t, _ = perf.poses(streamed)
    perf.inject_slip("head", 0.03, angle_deg=10.0)
    R2, t2, _ = perf.poses(streamed)
    assert np.array_equal(t, t2) and np.array_equal(R, R2)  # history is not rewritten
    _, t3, _ = perf.poses(np.array([1.0]))
    _, t4, _ = Performer(routine="walk", seed=1, noise=None).poses(np.array([1.0]))
    assert np.linalg.norm(t3[0, perf.model.index("head")] - t4[0, perf.model.index("head")]) == pytest.approx(0.03)


def test_runtime_faults_switch_on_and_off():
    perf = Performer(routine="walk", seed=4)
    times = np.arange(2000) / 100.0
    perf.set_dropout(0.1)
    assert 0.08 < 1 - perf.poses(times)[2].mean() < 0.12
    perf.set_unit_scale(1.05)
    perf.set_noise(None)
    exact = Performer(routine="walk", seed=4, noise=None).poses(times)[1]
    assert np.allclose(perf.poses(times)[1], exact * 1.05)
    perf.set_quantise(72.0)
    q = perf.poses(times)[1]
    step = 72 * 4 / 32768 * 0.0254
    assert np.allclose(q / step, np.round(q / step), atol=1e-6)
    perf.clear_faults()
    R, t, valid = perf.poses(times)
    assert valid.all() and np.array_equal(t, exact)


def test_faults_can_be_injected_while_another_thread_streams():
    perf = Performer(routine="walk", seed=5)
    errors = []

    def stream():
        try:
            for k in range(60):
                R, t, v = perf.poses(np.arange(k * 5, k * 5 + 5) / 100.0)
                assert t.shape == (5, 16, 3)
        except Exception as exc:  # noqa: BLE001 - the test reports whatever broke
            errors.append(exc)

    th = threading.Thread(target=stream)
    th.start()
    for k in range(20):
        perf.inject_slip(k % 16, 0.01)
        perf.set_dropout(0.01 * (k % 3))
    th.join()
    assert not errors and len(perf.slips) == 20


def test_simulate_returns_a_take_with_truth_for_the_chosen_birds():
    take, truth = simulate(model="human", motion="walk", seconds=2, rate_hz=100, birds=6, seed=1,
                           faults={"dropout": 0.05, "slip": {"sensor": "l_hand", "at_time": 1.0, "distance_m": 0.02}})  # fmt: skip
    assert take.names == ("pelvis", "chest", "head", "l_upper_arm", "l_forearm", "l_hand")
    assert take.n_frames == 200 and take.rate_hz == 100.0
    assert np.allclose(take.times, np.arange(200) / 100.0)
    assert 0.02 < 1 - take.valid.mean() < 0.09
    assert set(truth["parent"]) == set(take.names) - {"pelvis"}
    assert truth["slip_events"][0]["sensor"] == "l_hand" and truth["slip_events"][0]["time_s"] == 1.0
    after = {j["child"]: j for j in truth["after_slips"]["joints"]}
    before = {j["child"]: j for j in truth["joints"]}
    assert not np.allclose(after["l_hand"]["c"], before["l_hand"]["c"])
    assert np.allclose(after["l_forearm"]["c"], before["l_forearm"]["c"])


@pytest.mark.parametrize(
    "call",
    [
        lambda: Performer(noise="gaussian"),  # not a noise kind
        lambda: Performer(routine="jog"),  # not a routine
        lambda: Performer().inject_slip("tail", 0.02),  # no such sensor
        lambda: Performer().inject_slip(3, 2.0),  # a 2 m "slip"
        lambda: Performer().set_dropout(-0.1),  # negative probability
        lambda: simulate(seconds=1, faults={"teleport": 1}),  # unknown fault
        lambda: simulate(seconds=1, faults={"slip": {"sensor": "head"}}),  # slip without a distance
    ],
)
def test_bad_performer_requests_raise_a_simulator_error(call):
    with pytest.raises(SimulatorError):
        call()


def test_set_routine_switches_what_the_performer_does_next():
    perf = Performer(routine="exercise", seed=6, noise=None)
    perf.set_routine("idle")
    times = np.arange(0, 30, 0.05)
    _, t, _ = perf.poses(times)
    assert perf.motion.name == "idle"
    assert np.ptp(t, axis=0).max() < 0.15  # idle: every sensor stays within a few centimetres
