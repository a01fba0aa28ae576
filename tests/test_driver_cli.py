"""`flockcal record`, `replay` and `convert` end to end against the simulator (sim:// URL): every file
written is named on stderr, and the sensor names given to `record` travel with the recording."""

from __future__ import annotations

import os

import numpy as np
import pytest

from flockcal.cli import main
from flockcal.takes import load_take


NAMES = ["pelvis", "chest", "l_thigh", "r_thigh"]


def test_record_replay_convert_round_trip_keeps_the_sensor_names(tmp_path, capsys):
    raw, npz = tmp_path / "take.fobraw", tmp_path / "take.npz"
    url = "sim://cli-roundtrip?birds=4&rate=50&motion=walk"
    assert main(["record", "--port", url, "--birds", "4", "--rate", "50", "--names", ",".join(NAMES), "-o", str(raw),
                 "--seconds", "1"]) == 0
    err = capsys.readouterr().err
    assert f"wrote {raw}:" in err
    assert main(["replay", str(raw)]) == 0
    out = capsys.readouterr().out
    frames = int(out.split("\n")[1].split()[0])
    assert frames > 30
    assert f"sensors: {', '.join(NAMES)}" in out
    assert main(["convert", str(raw), "-o", str(npz)]) == 0
    assert f"wrote {npz}:" in capsys.readouterr().err
    take = load_take(npz)
    assert take.n_frames == frames and take.n_sensors == 4 and take.rate_hz == 50
    assert list(take.names) == NAMES
    assert np.all(np.diff(take.times) >= 0)
    # --names at convert time still wins (a recording named wrongly can be fixed without re-recording).
    assert main(["convert", str(raw), "-o", str(npz), "--names", "a,b,c,d"]) == 0
    assert list(load_take(npz).names) == ["a", "b", "c", "d"]


def test_unnamed_recording_converts_with_bird1_to_birdN(tmp_path, capsys):
    raw, npz = tmp_path / "take.fobraw", tmp_path / "take.npz"
    assert main(["record", "--port", "sim://cli-unnamed?birds=2&rate=50", "--birds", "2", "-o", str(raw),
                 "--seconds", "0.5"]) == 0
    assert main(["convert", str(raw), "-o", str(npz)]) == 0
    assert list(load_take(npz).names) == ["bird1", "bird2"]  # as FBB addresses and `flockcal serve` count


@pytest.mark.parametrize("names, message", [("a,b,c", "gives 3 names but there are 4 birds"),
                                            ("a,b,a,d", "must be unique"),
                                            ("a,b/c,d,e", "is not allowed")])
def test_bad_names_for_record_are_refused_before_anything_is_written(tmp_path, capsys, names, message):
    # Tried: too few names, a repeated name, a name with a slash.
    raw = tmp_path / "take.fobraw"
    assert main(["record", "--port", "sim://cli-badnames?birds=4", "--birds", "4", "--names", names, "-o", str(raw),
                 "--seconds", "0.5"]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1
    assert not list(tmp_path.iterdir())


def test_replay_of_a_truncated_recording_says_how_much_was_recovered(tmp_path, capsys):
    raw = tmp_path / "take.fobraw"
    url = "sim://cli-truncated?birds=2&rate=50"
    assert main(["record", "--port", url, "--birds", "2", "-o", str(raw), "--seconds", "0.6"]) == 0
    with open(raw, "r+b") as fh:
        fh.truncate(os.path.getsize(raw) - 5)
    capsys.readouterr()
    assert main(["replay", str(raw)]) == 0
    assert "recovered" in capsys.readouterr().err


def test_replay_of_a_file_that_is_not_a_recording_fails_with_one_line(tmp_path, capsys):
    # Tried: an .npz take passed to replay.
    bad = tmp_path / "x.fobraw"
    bad.write_bytes(b"PK\x03\x04 not a recording")
    assert main(["replay", str(bad)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "not a flockcal raw recording" in err


def test_record_from_a_port_that_does_not_exist_fails_with_one_line(capsys):
    # Tried: a device path with no device behind it.
    assert main(["record", "--port", "/dev/does-not-exist-fob", "-o", "/tmp/never.fobraw", "--seconds", "1"]) == 2
    err = capsys.readouterr().err
    assert "cannot open /dev/does-not-exist-fob" in err and err.count("\n") == 1
