"""Tracker unit scale (issue 8, part 3): from a simulated rigid pair with a known unit error, the
estimated factor is right to 0.2%, it can be applied to later takes, and a non-rigid pair is refused."""

from __future__ import annotations

import json

import numpy as np
import pytest

from flockcal.cli import main
from flockcal.commands.outputs import scale_factor
from flockcal.errors import FlockcalError
from flockcal.simulator.take import simulate
from flockcal.solver.scale import ScaleError, rigid_pair_scale
from flockcal.takes import load_take, save_take

UNIT_ERROR = 1.03  # the simulated tracker reports every range 3% long
DISTANCE = 0.565  # the paper's rigid pair


@pytest.fixture(scope="module")
def pair_take(tmp_path_factory):
    take, _ = simulate("pair", motion="walk", seconds=20, rate_hz=100, seed=4, faults={"unit_scale": UNIT_ERROR})
    path = tmp_path_factory.mktemp("scale") / "pair.npz"
    save_take(path, take)
    return take, path


def test_scale_of_rigid_pair_with_3_percent_unit_error_is_within_0_2_percent(pair_take):
    take, _ = pair_take
    est = rigid_pair_scale(
        take.positions[:, 0], take.positions[:, 1], DISTANCE, valid=take.valid.all(axis=1),
        rotations_a=take.rotations[:, 0], rotations_b=take.rotations[:, 1],
    )  # fmt: skip
    truth = 1 / UNIT_ERROR  # the factor that undoes the error
    assert abs(est.factor / truth - 1) < 0.002
    # The spread is reported and consistent: the scaled distances' std is the measured std times the factor.
    assert est.scaled_std_m == pytest.approx(est.measured_std_m * est.factor)
    assert 0 < est.factor_stderr < 0.002 * truth


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
    assert abs(report["factor"] * UNIT_ERROR - 1) < 0.002
    assert report["scaled_std_m"] > 0 and report["factor_stderr"] > 0
    scaled = load_take(out_path)
    d = np.linalg.norm(scaled.positions[:, 0] - scaled.positions[:, 1], axis=1)[scaled.valid.all(axis=1)]
    assert abs(d.mean() / DISTANCE - 1) < 0.002
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
