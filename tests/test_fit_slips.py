"""`flockcal fit` on a recorded take with a sensor slip: the slip is listed and that sensor's joints re-fitted."""

import json
import subprocess
import sys

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


def _cli(*argv, cwd):
    out = subprocess.run([sys.executable, "-m", "flockcal", *map(str, argv)], cwd=cwd, capture_output=True,
                         text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    return out.stdout


def test_bones_after_a_slip_are_the_distances_between_the_joint_centres_the_fit_reports(tmp_path):
    """A bone joins a joint refitted on the frames since a slip and one fitted on the whole take: here the
    right thigh's, from the hip (the thigh never slipped) to the knee (the shin slipped 2 cm at 20 s).
    Its length used to be the shin segment's own calibration's, whose hip came from 20 s of frames: 0.65 mm
    off the centres the same JSON lists, and a skeleton file of such a fit was refused as hand-edited."""
    _cli("simulate", "--motion", "exercise", "--seconds", "40", "--seed", "1", "--slip", "r_shin@20:20",
         "-o", "take.npz", cwd=tmp_path)
    d = json.loads(_cli("fit", "take.npz", "--json", cwd=tmp_path))
    assert [e["sensor"] for e in d["slip_events"]] == ["r_shin"], d["slip_events"]
    joint = {j["child"]: j for j in d["joints"]}
    start = {name: j.get("segment_start_s") for name, j in joint.items()}

    def ends(b):  # the bone's two joint centres in its body's sensor frame (docs/design.md §5)
        a = joint[b["body"]]["c"] if b["from_joint"] == b["body"] else joint[b["from_joint"]]["l"]
        return np.asarray(a), np.asarray(joint[b["to_joint"]]["l"])

    mixed = [b for b in d["bones"] if (start[b["from_joint"]] is None) != (start[b["to_joint"]] is None)]
    assert any(b["body"] == "r_thigh" for b in mixed), mixed  # the case that went wrong is in this take
    for b in d["bones"]:
        a, z = ends(b)
        # The JSON's own numbers: only the last bits of a square root between them.
        assert abs(b["length_m"] - np.linalg.norm(a - z)) < 1e-9, b
        # A bone carries the latest segment start of its two joints, and none when neither was refitted.
        starts = [s for s in (start[b["from_joint"]], start[b["to_joint"]]) if s is not None]
        assert b.get("segment_start_s") == (max(starts) if starts else None), b
