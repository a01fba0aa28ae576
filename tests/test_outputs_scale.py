"""Tracker unit scale: from a simulated rigid pair with a known unit error the estimated factor holds
docs/outputs.md's "within 0.04 % of the truth", it can be applied to later takes, and a pair that is not
rigid (its distance or its relative rotation varies) is refused."""

from __future__ import annotations

import json

import numpy as np
import pytest

from scipy.spatial.transform import Rotation

from flockcal.cli import main
from flockcal.commands.outputs import scale_factor
from flockcal.errors import FlockcalError
from flockcal.simulator.take import simulate
from flockcal.solver.scale import ScaleError, rigid_pair_scale
from flockcal.takes import load_take, save_take

UNIT_ERROR = 1.03  # the simulated tracker reports every range 3% long
DISTANCE = 0.565  # the paper's rigid pair
# docs/outputs.md claims the factor within 0.04 % of the truth (worst of 12 seeds measured: 0.040 %); the
# computation is deterministic for a seed, so the margin only covers floating-point differences between
# BLAS builds and a seed that lands a little past the measured worst: 0.01 %.
FACTOR_TOL = 0.0004 + 0.0001


@pytest.fixture(scope="module")
def pair_take(tmp_path_factory):
    take, _ = simulate("pair", motion="walk", seconds=20, rate_hz=100, seed=4, faults={"unit_scale": UNIT_ERROR})
    path = tmp_path_factory.mktemp("scale") / "pair.npz"
    save_take(path, take)
    return take, path


def test_scale_of_rigid_pair_with_3_percent_unit_error_is_within_0_04_percent(pair_take):
    take, _ = pair_take
    est = rigid_pair_scale(
        take.positions[:, 0], take.positions[:, 1], DISTANCE, valid=take.valid.all(axis=1),
        rotations_a=take.rotations[:, 0], rotations_b=take.rotations[:, 1],
    )  # fmt: skip
    truth = 1 / UNIT_ERROR  # the factor that undoes the error
    assert abs(est.factor / truth - 1) < FACTOR_TOL
    # The reported spread is the std of the corrected distances, computed here from the positions
    # themselves (an independent oracle: the test applies the factor and measures).
    keep = take.valid.all(axis=1)
    corrected = est.factor * np.linalg.norm(take.positions[keep, 0] - take.positions[keep, 1], axis=1)
    assert est.scaled_std_m == pytest.approx(corrected.std(ddof=1), rel=1e-9)
    assert corrected.mean() == pytest.approx(DISTANCE, rel=1e-12)
    # The stated standard error is honest: the true error is within 3 of them, and it is no looser
    # than the claim itself.
    assert abs(est.factor - truth) < 3 * est.factor_stderr
    assert est.factor_stderr < FACTOR_TOL * truth


def test_scale_command_prints_factor_and_spread_as_json_and_rescales_a_later_take(pair_take, tmp_path, capsys):
    _, path = pair_take
    later, _ = simulate("pair", motion="walk", seconds=5, rate_hz=100, seed=9, faults={"unit_scale": UNIT_ERROR})
    later_path, out_path = tmp_path / "later.npz", tmp_path / "later_scaled.npz"
    save_take(later_path, later)
    rc = main(["scale", str(path), "--distance", str(DISTANCE), "--sensors", "sensor_a,sensor_b", "--json",
               "--apply", str(later_path), "-o", str(out_path)])  # fmt: skip
    assert rc == 0
    report = json.loads(capsys.readouterr().out)
    assert report["sensors"] == ["sensor_a", "sensor_b"]
    assert abs(report["factor"] * UNIT_ERROR - 1) < FACTOR_TOL
    assert report["scaled_std_m"] > 0 and report["factor_stderr"] > 0
    # The corrected copy is the later take's positions times the factor (about the transmitter), nothing else.
    scaled = load_take(out_path)
    np.testing.assert_allclose(scaled.positions, later.positions * report["factor"], rtol=1e-12)
    np.testing.assert_array_equal(scaled.rotations, later.rotations)
    d = np.linalg.norm(scaled.positions[:, 0] - scaled.positions[:, 1], axis=1)[scaled.valid.all(axis=1)]
    # 5 s of a noisy pair: its mean distance carries its own noise (about 0.05 %), so 0.1 % here.
    assert abs(d.mean() / DISTANCE - 1) < 0.001
    # The saved JSON is itself a valid --scale argument for fit/report/export-bvh.
    js = tmp_path / "scale.json"
    js.write_text(json.dumps(report))
    assert scale_factor(str(js)) == report["factor"]


def test_scale_refuses_sensors_that_are_not_rigidly_fixed(tmp_path, capsys):
    # Tried: a human take, using a hand and a foot sensor as if they were a rigid pair.
    take, _ = simulate("human", motion="walk", seconds=4, rate_hz=50, seed=2, birds=16)
    hand = next(n for n in take.names if "hand" in n)
    foot = next(n for n in take.names if "foot" in n)
    a, b = take.index(hand), take.index(foot)
    with pytest.raises(ScaleError, match="not look rigidly fixed"):
        rigid_pair_scale(take.positions[:, a], take.positions[:, b], DISTANCE, valid=take.valid[:, a] & take.valid[:, b])
    path = tmp_path / "human.npz"
    save_take(path, take)
    assert main(["scale", str(path), "--distance", "0.565", "--sensors", f"{hand},{foot}"]) == 2
    err = capsys.readouterr().err
    assert "rigid" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1


def test_scale_refuses_a_nonsense_distance_and_a_bad_scale_argument(pair_take):
    take, _ = pair_take
    # Tried: a negative known distance.
    with pytest.raises(ScaleError, match="positive"):
        rigid_pair_scale(take.positions[:, 0], take.positions[:, 1], -0.5)
    # Tried: --scale given a word that is neither a number nor a file.
    with pytest.raises(FlockcalError, match="neither a number"):
        scale_factor("big")


def test_scale_refuses_a_pair_whose_distance_holds_but_whose_sensors_turn_against_each_other(pair_take):
    # Tried: the rigid pair's positions (distance constant to the tracker's noise) with sensor b's
    # orientation swinging ±25° about an axis of its own relative to sensor a — two sensors on a hinge
    # 56.5 cm apart, not on one bar. docs/outputs.md: refused above 10° RMS.
    take, _ = pair_take
    n = take.n_frames
    swing = Rotation.from_rotvec(np.outer(np.radians(25) * np.sin(np.linspace(0, 12 * np.pi, n)), [0.0, 0.0, 1.0]))
    turned = (Rotation.from_matrix(take.rotations[:, 1]) * swing).as_matrix()
    keep = take.valid.all(axis=1)
    with pytest.raises(ScaleError, match=r"turn \d+(\.\d)?° \(RMS\)"):
        rigid_pair_scale(take.positions[:, 0], take.positions[:, 1], DISTANCE, valid=keep,
                         rotations_a=take.rotations[:, 0], rotations_b=turned)  # fmt: skip
    # The same pair turning 5° RMS (a loose strap, still one bar) is measured, not refused.
    small = Rotation.from_rotvec(np.outer(np.radians(5 * np.sqrt(2)) * np.sin(np.linspace(0, 12 * np.pi, n)), [0.0, 0.0, 1.0]))
    est = rigid_pair_scale(take.positions[:, 0], take.positions[:, 1], DISTANCE, valid=keep,
                           rotations_a=take.rotations[:, 0],
                           rotations_b=(Rotation.from_matrix(take.rotations[:, 1]) * small).as_matrix())  # fmt: skip
    assert 4.0 < est.rotation_spread_deg < 6.0
