"""TRC (issue 47, item 6): `flockcal fit TAKE --trc FILE` writes the fitted joint centres as virtual
markers over the take, in millimetres, as OpenSim's TRCFileAdapter reads it.

The file is parsed here by the layout OpenSim's reader expects (five header lines, a blank one, then rows
of Frame#, Time and X Y Z per marker; a missing marker three empty fields), and each knee marker is checked
against the fitted centre computed here from the take and `fit --json`'s c and l: the midpoint of the
shin's and the thigh's copies of the knee, every frame, Y-up millimetres (docs/outputs.md). OpenSim's own
reader (the `opensim` wheel, where it installs) loads the file and reads the same numbers.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from test_outputs_gltf import flockcal

# docs/outputs.md: positions are written to 0.001 mm; the check allows that rounding (0.0005) twice over.
CLAIM_MM = 1e-3
# The Flock's world (Z down) turned Y-up as docs/outputs.md says: (x, y, z) → (x, −z, y).
TRACKER_TO_FILE = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])


def parse_trc(text: str) -> dict:
    """The header fields, marker labels, frame numbers, times and (n, k, 3) positions (NaN where empty)."""
    lines = text.split("\n")
    first = lines[0].split("\t")
    assert first[:3] == ["PathFileType", "4", "(X/Y/Z)"]
    keys, values = lines[1].split("\t"), lines[2].split("\t")
    assert keys == ["DataRate", "CameraRate", "NumFrames", "NumMarkers", "Units", "OrigDataRate",
                    "OrigDataStartFrame", "OrigNumFrames"]
    header = dict(zip(keys, values))
    labels = lines[3].split("\t")
    assert labels[:2] == ["Frame#", "Time"]
    markers = [x for x in labels[2:] if x]
    k = len(markers)
    assert labels[2:] == [x for m in markers for x in (m, "", "")] + [""]  # each label then two tabs more
    assert lines[4].split("\t") == ["", ""] + [f"{a}{i}" for i in range(1, k + 1) for a in "XYZ"] + [""]
    assert lines[5] == ""
    rows = [line.split("\t") for line in lines[6:] if line]
    assert lines[-1] == "" and all(len(r) == 2 + 3 * k + 1 and r[-1] == "" for r in rows)  # rows end in a tab
    cells = np.array([[float(x) if x else np.nan for x in r[:-1]] for r in rows])
    return {"header": header, "markers": markers, "frame": cells[:, 0], "time": cells[:, 1],
            "xyz": cells[:, 2:].reshape(len(rows), k, 3), "file": first[3]}


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    folder = tmp_path_factory.mktemp("trc")
    sim = flockcal("simulate", "--model", "human", "--motion", "exercise", "--seconds", "8", "--rate", "50",
                   "--seed", "7", "--dropout", "0.02", "-o", "take.npz", cwd=folder)
    assert sim.returncode == 0, sim.stderr
    fit = flockcal("fit", "take.npz", "--no-slips", "--json", "--trc", "take.trc", cwd=folder)
    assert fit.returncode == 0, fit.stderr
    with np.load(folder / "take.npz") as z:
        take = {k: z[k] for k in z.files}
    return folder, json.loads(fit.stdout), parse_trc((folder / "take.trc").read_text()), take


def test_header_says_the_rate_frames_markers_and_millimetres(run):
    _, fit, trc, take = run
    n = len(take["rotations"])
    h = trc["header"]
    assert float(h["DataRate"]) == float(h["CameraRate"]) == float(h["OrigDataRate"]) == float(take["rate_hz"])
    assert int(h["NumFrames"]) == int(h["OrigNumFrames"]) == n and h["OrigDataStartFrame"] == "1"
    assert h["Units"] == "mm" and trc["file"] == "take.trc"
    joints = [j for j in fit["joints"] if fit["parent"].get(j["child"]) == j["parent"]]
    assert int(h["NumMarkers"]) == len(trc["markers"]) == len(joints) == 15
    np.testing.assert_array_equal(trc["frame"], np.arange(1, n + 1))
    times = take["times"] - take["times"][0] if "times" in take else np.arange(n) / float(take["rate_hz"])
    np.testing.assert_allclose(trc["time"], times, atol=5e-7)
    # Markers are named by joint, one word each.
    assert {"left_knee", "right_knee", "left_elbow", "right_elbow", "left_hip", "right_hip", "left_ankle",
            "right_wrist", "neck", "left_shoulder"} <= set(trc["markers"])
    assert all(m.replace("_", "").isalnum() for m in trc["markers"]) and len(set(trc["markers"])) == 15


@pytest.mark.parametrize("side", ["l", "r"])
def test_knee_marker_is_the_fitted_centre_every_frame(run, side):
    _, fit, trc, take = run
    names = [str(x) for x in take["names"]]
    shin, thigh = f"{side}_shin", f"{side}_thigh"
    entry = [j for j in fit["joints"] if {j["child"], j["parent"]} == {shin, thigh}][0]
    at = {entry["child"]: np.array(entry["c"]), entry["parent"]: np.array(entry["l"])}
    R, t, valid = take["rotations"], take["positions"], take["valid"]
    a = np.einsum("nij,j->ni", R[:, names.index(shin)], at[shin]) + t[:, names.index(shin)]
    b = np.einsum("nij,j->ni", R[:, names.index(thigh)], at[thigh]) + t[:, names.index(thigh)]
    want = (a + b) / 2 @ TRACKER_TO_FILE.T * 1000.0
    both = valid[:, names.index(shin)] & valid[:, names.index(thigh)]
    assert (~both).sum() > 0  # the take has dropouts at this knee: a missing marker is tried too
    got = trc["xyz"][:, trc["markers"].index(f"{'left' if side == 'l' else 'right'}_knee")]
    assert np.isnan(got[~both]).all() and np.isfinite(got[both]).all()
    np.testing.assert_allclose(got[both], want[both], atol=CLAIM_MM, rtol=0)


def test_chunked_writer_is_the_whole_take_writer(run):
    """The service writes the TRC from its frame log a chunk at a time: 7 frames at a time gives the bytes
    one pass over the whole take gives."""
    from flockcal.exports.trc import trc_chunks, trc_text
    from flockcal.takes import load_take

    folder, fit, _, _ = run
    take = load_take(folder / "take.npz")
    whole = trc_text(fit, take, file_name="take.trc")
    assert "".join(trc_chunks(fit, take, file_name="take.trc", chunk_frames=7)) == whole
    assert whole == (folder / "take.trc").read_text()


def test_opensim_reads_it(run):
    try:
        import opensim
    except ImportError:
        if os.environ.get("CI"):
            pytest.fail("CI installs the opensim wheel (pyproject.toml's test extra, Linux x86_64)")
        pytest.skip("OpenSim's Python package is not installed (its wheels are for Linux x86_64, Python 3.11–3.13: "
                    "pip install opensim)")
    opensim.Logger.removeFileSink()  # else OpenSim writes opensim.log into the working folder
    folder, _, trc, _ = run
    table = opensim.TimeSeriesTableVec3(str(folder / "take.trc"))
    assert table.getNumRows() == len(trc["time"]) and list(table.getColumnLabels()) == trc["markers"]
    assert table.getTableMetaDataAsString("Units") == "mm"
    times = np.array([table.getIndependentColumn()[i] for i in range(table.getNumRows())])
    np.testing.assert_array_equal(times, trc["time"])
    for k, name in enumerate(trc["markers"]):
        col = table.getDependentColumn(name)
        got = np.array([[col[i][a] for a in range(3)] for i in range(table.getNumRows())])
        np.testing.assert_array_equal(got, trc["xyz"][:, k], err_msg=name)  # NaN where the file has no value
    # The reader OpenSim's Scale tool takes its markers from.
    data = opensim.MarkerData(str(folder / "take.trc"))
    assert data.getNumFrames() == len(trc["time"]) and data.getUnits().getAbbreviation() == "mm"


def test_a_calibration_with_no_joint_is_one_line(run, tmp_path):
    # Tried: a fit whose sensors all ride rigidly together (no joint at all) handed to the writer.
    from flockcal.exports.trc import TrcError, trc_text
    from flockcal.takes import load_take

    folder, fit, _, _ = run
    take = load_take(folder / "take.npz")
    rigid = dict(fit, joints=[], rigid_groups=[list(fit["sensors"])])
    with pytest.raises(TrcError, match="no fitted joint"):
        trc_text(rigid, take)
