"""`flockcal fit` on a recorded take with a sensor slip: the slip is listed and that sensor's joints re-fitted."""

import json

import numpy as np
import pytest

from flockcal.cli import main


@pytest.fixture(scope="module")
def slipped_take(tmp_path_factory):
    out = tmp_path_factory.mktemp("slip") / "take.npz"
    assert main(["simulate", "--motion", "walk", "--seconds", "25", "--seed", "3",
                 "--slip", "l_forearm@12:20", "-o", str(out)]) == 0
    return out


def test_fit_json_lists_the_slip_and_refits_the_slipped_sensors_joints(slipped_take, capsys):
    capsys.readouterr()
    assert main(["fit", str(slipped_take), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    (ev,) = d["slip_events"]
    assert ev["sensor"] == "l_forearm" and abs(ev["time_s"] - 12.0) < 0.5 and 10 < ev["jump_mm"] < 30
    refit = {j["child"] for j in d["joints"] if j.get("segment_start_s") is not None}
    assert refit == set(ev["joints"]) and "l_forearm" in refit
    # Joints away from the slipped sensor keep the whole take.
    assert all(j.get("segment_start_s") is None for j in d["joints"] if j["child"] in ("r_forearm", "l_shin"))
    truth = json.loads(slipped_take.with_name("take.truth.json").read_text())
    # simulator/take.py writes `after_slips` (the truth once every slip has happened) whenever a slip was
    # scheduled; without it the elbow check below would be skipped, so its absence fails.
    assert "after_slips" in truth, sorted(truth)
    after = {j["child"]: j for j in truth["after_slips"]["joints"]}
    # The re-fitted elbow sits near the new truth across its hinge axis.
    j = next(j for j in d["joints"] if j["child"] == "l_forearm")
    axis = np.asarray(j["axis_child"]) if j["axis_child"] else np.zeros(3)
    err = np.asarray(j["c"]) - np.asarray(after["l_forearm"]["c"])
    assert np.linalg.norm(err - axis * (err @ axis)) < 0.01


def test_fit_table_names_the_slip_and_no_slips_skips_the_search(slipped_take, capsys):
    capsys.readouterr()
    assert main(["fit", str(slipped_take)]) == 0
    out = capsys.readouterr().out
    assert "Sensor slips" in out and "slip of l_forearm" in out
    assert main(["fit", str(slipped_take), "--json", "--no-slips"]) == 0
    assert json.loads(capsys.readouterr().out)["slip_events"] == []
