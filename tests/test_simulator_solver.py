"""The solver against simulated truth (issue 3's acceptance): exact bones on exact data, millimetres
with tracker noise, the right tree, and coverage that tells "idle" from "exercise"."""

import numpy as np
import pytest

from flockcal.simulator.take import simulate
from flockcal.solver.accumulator import GramAccumulator
from flockcal.solver.calibration import calibrate
from flockcal.solver.fits import pair_fits


def _accumulate(take):
    acc = GramAccumulator(take.n_sensors)
    acc.add_poses(take.rotations, take.positions, take.valid)
    return acc


def _joint_errors(fit: dict, truth: dict) -> dict:
    """Per joint (by child name): distance of fitted c and l from truth; for a hinge, from the true axis
    (a hinge's centre is anywhere on its axis; the solver picks the point nearest the sensors)."""
    got = {j["child"]: j for j in fit["joints"]}
    out = {}
    for j in truth["joints"]:
        f = got[j["child"]]
        assert f["parent"] == j["parent"]
        errs = []
        for key, axis in (("c", "axis_child"), ("l", "axis_parent")):
            d = np.subtract(f[key], j[key])
            if j["hinge"]:
                a = np.asarray(j[axis])
                d = d - a * (a @ d)
            errs.append(np.linalg.norm(d))
        out[j["child"]] = max(errs)
    return out


def _bone_errors(fit: dict, truth: dict) -> dict:
    """Bone length errors for bones between two ball joints (the ones a hinge does not leave ambiguous)."""
    hinges = {j["child"] for j in truth["joints"] if j["hinge"]}
    got = {(b["body"], b["from_joint"], b["to_joint"]): b["length_m"] for b in fit["bones"]}
    got.update({(b, t, f): v for (b, f, t), v in list(got.items())})  # root bones in either order
    return {
        (b["body"], b["from_joint"], b["to_joint"]): abs(got[(b["body"], b["from_joint"], b["to_joint"])] - b["length_m"])
        for b in truth["bones"]
        if not {b["from_joint"], b["to_joint"]} & hinges
    }


def _axis_distance_errors(fit: dict, truth: dict) -> list[float]:
    """For bones ending at a hinge: the other joint's distance from the hinge axis (defined even though
    the hinge point itself is not), in the body's sensor frame."""
    fj = {j["child"]: j for j in fit["joints"]}
    tj = {j["child"]: j for j in truth["joints"]}
    errs = []
    for h, j in tj.items():
        if not j["hinge"]:
            continue
        body = j["parent"]  # the hinge's parent body also holds its own inboard joint
        if body not in tj:
            continue

        def dist(joints, axis_key):
            a = np.asarray(tj[h][axis_key])
            d = np.subtract(joints[body]["c"], joints[h]["l"])
            return np.linalg.norm(d - a * (a @ d))

        errs.append(abs(dist(fj, "axis_parent") - dist(tj, "axis_parent")))
    return errs


@pytest.fixture(scope="module")
def exact_exercise():
    # Exact data means rigid sensors too: soft tissue (on by default) moves each sensor with the pose,
    # and these promises are about the solver recovering fixed placements to 1e-9 m.
    return simulate(model="human", motion="exercise", seconds=40, rate_hz=60, seed=2, noise=None, sta_mm=0)


def test_solver_recovers_joints_and_bones_to_1e_9_m_on_exact_data(exact_exercise):
    take, truth = exact_exercise
    fit = calibrate(_accumulate(take), hierarchy=truth["parent"], names=take.names).to_dict()
    assert max(_joint_errors(fit, truth).values()) < 1e-9
    bones = _bone_errors(fit, truth)
    assert len(bones) >= 6 and max(bones.values()) < 1e-9
    axis = _axis_distance_errors(fit, truth)
    assert len(axis) == 4 and max(axis) < 1e-9


def test_solver_finds_the_true_tree_on_exact_data(exact_exercise):
    take, truth = exact_exercise
    fit = calibrate(_accumulate(take), root="pelvis", names=take.names).to_dict()
    assert fit["parent"] == truth["parent"]
    hinges = {j["child"] for j in fit["joints"] if j["hinge"]}
    assert hinges == {j["child"] for j in truth["joints"] if j["hinge"]}


def test_linkage_bones_are_exact_to_1e_9_m():
    take, truth = simulate(model="linkage", motion="exercise", seconds=30, rate_hz=50, seed=3, noise=None)
    fit = calibrate(_accumulate(take), names=take.names, root="link0").to_dict()
    assert fit["parent"] == truth["parent"]
    bones = _bone_errors(fit, truth)
    assert len(bones) == 4 and max(bones.values()) < 1e-9


def test_solver_is_within_a_millimetre_on_exercise_with_tracker_noise():
    # docs/simulator.md: on this take (rigid sensors, tracker noise, seed 1) every joint centre within 1 mm
    # (median 0.25 mm), bones between ball joints within 1 mm, a hinge-ended bone's axis distance within
    # 0.5 mm. The fit is deterministic for a seed: the margin (0.2 mm, 0.1 mm for the median) covers
    # floating-point differences between BLAS builds, not machine load. The truth holds each sensor's rest
    # placement, which soft tissue would move the sensors away from, hence sta_mm=0.
    take, truth = simulate(model="human", motion="exercise", seconds=45, rate_hz=100, seed=1, noise="tracker",
                           sta_mm=0)
    fit = calibrate(_accumulate(take), root="pelvis", names=take.names).to_dict()
    assert fit["parent"] == truth["parent"]
    joints = np.array(list(_joint_errors(fit, truth).values()))
    assert joints.max() < 0.001 + 0.0002 and np.median(joints) < 0.00025 + 0.0001
    assert max(_bone_errors(fit, truth).values()) < 0.001 + 0.0002
    assert max(_axis_distance_errors(fit, truth)) < 0.0005 + 0.0002
    assert all(j["determined"] for j in fit["joints"])


def _coverage(motion):
    take, truth = simulate(model="human", motion=motion, seconds=45, rate_hz=40, seed=4, noise="tracker")
    names = list(take.names)
    pairs = np.array([[names.index(j["child"]), names.index(j["parent"])] for j in truth["joints"]])
    fits = pair_fits(_accumulate(take), pairs)
    hinge = np.array([j["hinge"] for j in truth["joints"]])
    return fits.coverage, hinge


def test_idle_gives_low_coverage_on_every_joint_and_exercise_high():
    idle, _ = _coverage("idle")
    exercise, hinge = _coverage("exercise")
    assert idle.max() < 0.002
    # Ball joints turned about all three axes; hinges about their one (coverage is sorted ascending).
    assert exercise[~hinge, 0].min() > 0.005
    assert exercise[hinge, 2].min() > 0.005
    assert exercise[hinge, 0].max() < 1e-3


def test_the_simulated_unit_scale_fault_lengthens_every_range_3_percent():
    # A simulator test (the solver's scale estimate is held in test_outputs_scale.py): the fault the scale
    # tests rely on really stretches the measured distance by the factor asked for.
    take, truth = simulate(model="pair", motion="walk", seconds=20, rate_hz=50, seed=5, faults={"unit_scale": 1.03})
    measured = np.linalg.norm(take.positions[:, 1] - take.positions[:, 0], axis=1).mean()
    assert measured / truth["sensor_distance_m"] == pytest.approx(1.03, abs=0.002)
