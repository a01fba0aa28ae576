"""`flockcal simulate`: writes a take with truth beside it, or serves the fake tracker on a real pty."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest
import serial

from flockcal.cli import main
from flockcal.simulator.performer import Performer
from flockcal.takes import load_take
from processes import reaped


def test_simulate_writes_the_npz_take_and_truth_json_beside_it(tmp_path, capsys):
    out = tmp_path / "take.npz"
    rc = main(["simulate", "--motion", "exercise", "--seconds", "3", "--birds", "6", "--seed", "1", "-o", str(out)])
    assert rc == 0
    take = load_take(out)
    assert take.names == ("pelvis", "chest", "head", "l_upper_arm", "l_forearm", "l_hand")
    assert take.n_frames == 300 and take.rate_hz == 100.0
    truth = json.loads((tmp_path / "take.truth.json").read_text())
    assert truth["parent"] == {"chest": "pelvis", "head": "chest", "l_upper_arm": "chest",
                               "l_forearm": "l_upper_arm", "l_hand": "l_forearm"}  # fmt: skip
    assert truth["simulation"]["motion"] == "exercise" and truth["simulation"]["seed"] == 1
    err = capsys.readouterr().err  # every file written is named on stderr
    assert f"wrote {out}" in err and "take.truth.json" in err


def test_simulate_options_reach_the_take(tmp_path):
    out = tmp_path / "faulty.npz"
    rc = main(["simulate", "--seconds", "2", "--birds", "4", "--noise", "none", "--dropout", "0.1",
               "--slip", "head@1:25", "--quantise", "72", "-o", str(out)])  # fmt: skip
    assert rc == 0
    take = load_take(out)
    truth = json.loads((tmp_path / "faulty.truth.json").read_text())
    assert 0.05 < 1 - take.valid.mean() < 0.15
    assert truth["slip_events"][0]["sensor"] == "head" and truth["slip_events"][0]["jump_mm"] == pytest.approx(25)
    step = 72 * 4 / 32768 * 0.0254
    assert np.allclose(take.positions / step, np.round(take.positions / step), atol=1e-6)


@pytest.mark.parametrize(
    "argv",
    [
        ["--slip", "l_hand-at-3s"],  # malformed slip spec
        ["--slip", "tail@1:20"],  # slip on a sensor the body does not have
        ["--birds", "40"],  # more birds than bodies
        ["--rate", "400"],  # faster than the tracker measures
        ["-o", "take.csv"],  # not an .npz name
        ["-o", "/nonexistent-dir/take.npz"],  # a directory that does not exist
    ],
)
def test_bad_simulate_input_exits_2_with_one_line(argv, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(["simulate", "--seconds", "1", *argv]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("flockcal simulate: error:")


def _word(lo: int, hi: int) -> int:
    w = ((hi & 0x7F) << 9) | ((lo & 0x7F) << 2)
    return w - 65536 if w & 0x8000 else w


def test_simulate_pty_serves_a_fake_tracker_that_answers_point(tmp_path):
    proc = subprocess.Popen(
        [sys.executable, "-m", "flockcal", "simulate", "--pty", "--birds", "2", "--noise", "none", "--seed", "3"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    with reaped(proc):  # Ctrl-C on leaving, as a user stops it; killed if it does not go
        device = proc.stdout.readline().strip()
        assert device and os.path.exists(device), proc.stderr.read()
        with serial.Serial(device, 115200, timeout=2.0) as port:
            port.reset_input_buffer()
            port.write(b"B")  # POINT: one POSITION/ANGLES record from the master bird
            record = port.read(12)
        assert len(record) == 12
        assert record[0] & 0x80 and not any(b & 0x80 for b in record[1:])  # phasing bit on byte 0 only
        inches = np.array([_word(record[k], record[k + 1]) for k in (0, 2, 4)]) * 72.0 / 32768
        pelvis = Performer(birds=2, seed=3, noise=None).poses(np.array([0.0]))[1][0, 0]
        # It is the performer's pelvis sensor (a few cm of motion since start aside), at the 72-inch scale.
        assert np.linalg.norm(inches * 0.0254 - pelvis) < 0.2
    assert proc.returncode == 0  # Ctrl-C is the documented way to stop it: a clean exit


def test_the_record_line_simulate_pty_prints_fits_the_fake_and_keeps_its_names(tmp_path):
    # The README tour: `flockcal simulate --pty`, then the `flockcal record` it suggests, then convert.
    proc = subprocess.Popen([sys.executable, "-m", "flockcal", "simulate", "--pty", "--motion", "exercise"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    with reaped(proc):
        device = proc.stdout.readline().strip()
        proc.stderr.readline()
        suggested = proc.stderr.readline().strip()
        assert suggested.startswith("record it with: flockcal record --port " + device), suggested
        argv = suggested.split(": ", 1)[1].split()[1:]
        argv[argv.index("recorded.fobraw")] = str(tmp_path / "recorded.fobraw")
        rec = subprocess.run([sys.executable, "-m", "flockcal", *argv, "--seconds", "4"], capture_output=True,
                             text=True, timeout=120)
    assert rec.returncode == 0, rec.stderr
    # The tracker's own 72-inch scale is kept (nothing saturates) and the line carries the rate asked.
    assert "72-inch scale (the tracker's own)" in rec.stderr
    assert "frames/s arrive" not in rec.stderr and "saturated" not in rec.stderr and "warning" not in rec.stderr
    npz = tmp_path / "recorded.npz"
    conv = subprocess.run([sys.executable, "-m", "flockcal", "convert", str(tmp_path / "recorded.fobraw"), "-o", str(npz)],
                          capture_output=True, text=True, timeout=120)
    assert conv.returncode == 0, conv.stderr
    take = load_take(npz)
    assert take.names == Performer(birds=16, seed=1).names
    assert take.valid.mean() > 0.97  # a few bird-frames at the ends of the stream, none beyond full scale
