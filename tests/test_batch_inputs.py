"""`flockcal batch` before any cluster starts, and the --combine rule for slips: what a missing Dask, clashing
names, bad options, a path that does not exist and an empty folder say (one line, exit 2, nothing written,
no cluster), how folders and globs expand, and which frames a slipped sensor contributes to the combined
sums. None of these needs Dask: they pass where the batch extra is not installed."""

import subprocess
import sys

import numpy as np
import pytest

from flockcal.cli import main
from flockcal.commands.batch import expand
from flockcal.commands.batch_tasks import contribution_mask
from flockcal.takes import make_take


def _one_line_error(capsys, argv):
    rc = main(argv)
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1, err
    return err


def test_without_dask_the_error_names_the_extra_to_install(tmp_path, capsys, monkeypatch):
    # As if dask.distributed were not installed: importing it fails.
    monkeypatch.setitem(sys.modules, "distributed", None)
    monkeypatch.setitem(sys.modules, "dask.distributed", None)
    (tmp_path / "t.npz").write_bytes(b"")
    err = _one_line_error(capsys, ["batch", str(tmp_path / "t.npz"), "-o", str(tmp_path / "out")])
    assert "flockcal batch runs on Dask" in err and "pip install 'flockcal[batch]'" in err
    assert not (tmp_path / "out").exists()


def test_two_takes_with_one_stem_are_refused_before_anything_runs(tmp_path, capsys):
    for d in ("mon", "tue"):
        (tmp_path / d).mkdir()
        (tmp_path / d / "warmup.npz").write_bytes(b"")
    err = _one_line_error(capsys, ["batch", str(tmp_path / "mon"), str(tmp_path / "tue"), "-o", str(tmp_path / "out")])
    assert "warmup.npz" in err and "would both write DIR/warmup.json" in err
    # --combine writes combined.json: a take of that name would be overwritten by it.
    (tmp_path / "combined.npz").write_bytes(b"")
    err = _one_line_error(capsys, ["batch", str(tmp_path / "combined.npz"), "-o", str(tmp_path / "o"), "--combine"])
    assert "combined.json" in err


@pytest.mark.parametrize("option, message", [(["--workers", "0"], "--workers must be 1 or more"),
                                             (["--tolerance-mm", "-1"], "--tolerance-mm must be a positive"),
                                             (["--timeout", "0"], "--timeout must be a positive")])
def test_bad_options_are_one_line(tmp_path, capsys, option, message):
    (tmp_path / "a.npz").write_bytes(b"")
    assert message in _one_line_error(capsys, ["batch", str(tmp_path / "a.npz"), "-o", str(tmp_path / "o"), *option])


def test_folders_are_searched_globs_expanded_and_each_file_taken_once(tmp_path, monkeypatch):
    for rel in ("day1/a.npz", "day1/deep/b.fobraw", "day1/notes.txt", "day2/c.c3d", "day2/d.npz"):
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_bytes(b"")
    monkeypatch.chdir(tmp_path)
    got = expand(["day1", "day2/*.npz", "day1/a.npz"])
    assert [name for name, _ in got] == ["day1/a.npz", "day1/deep/b.fobraw", "day2/d.npz"]
    assert got[0][1] == str(tmp_path / "day1" / "a.npz")  # absolute: workers run in other folders


def _batch(*argv, cwd):
    """`flockcal batch` as a user runs it, in a subprocess."""
    return subprocess.run([sys.executable, "-m", "flockcal", "batch", *map(str, argv)], cwd=cwd,
                          capture_output=True, text=True, timeout=120)


@pytest.mark.parametrize("given, says", [
    # tried: a file that does not exist beside a real one
    (["a.npz", "missing.npz"], "missing.npz: no such file or folder"),
    # tried: an empty folder (it read "0 of 1 takes fitted" after starting a cluster)
    (["empty"], "empty: no take (.npz, .fobraw, .c3d) in this folder"),
    # tried: a folder holding no take file, only notes
    (["notes"], "notes: no take (.npz, .fobraw, .c3d) in this folder"),
    # tried: a quoted glob that matches nothing
    (["day3/*.npz"], "day3/*.npz: no take file (.npz, .fobraw, .c3d) matches"),
])
def test_a_path_with_no_take_is_a_usage_error_before_any_cluster(tmp_path, given, says):
    (tmp_path / "a.npz").write_bytes(b"")
    (tmp_path / "empty").mkdir()
    (tmp_path / "notes").mkdir()
    (tmp_path / "notes" / "readme.txt").write_text("takes come tomorrow")
    run = _batch(*given, "-o", "out", cwd=tmp_path)
    assert run.returncode == 2, run.stderr
    assert run.stderr.count("\n") == 1 and run.stderr.startswith("flockcal batch: error: "), run.stderr
    assert says in run.stderr and "Traceback" not in run.stderr
    # Nothing started and nothing written: no cluster line, no results folder.
    assert "cluster" not in run.stderr and not (tmp_path / "out").exists()


def test_a_slipped_sensor_contributes_only_its_frames_from_before_the_slip(tmp_path):
    n, m = 1000, 4
    R = np.broadcast_to(np.eye(3), (n, m, 3, 3))
    take = make_take(R, np.zeros((n, m, 3)), ["a", "b", "c", "d"], 100.0)  # times 0.00 … 9.99 s
    slip = {"kind": "slip", "time_s": 6.0, "sensor": "b", "candidates": ["b"]}
    swap = {"kind": "swap", "time_s": 8.0, "sensor": "c", "candidates": ["c", "d"]}
    v = contribution_mask(take, [slip, swap])
    # docs/batch.md: a slipped sensor's frames count until 0.5 s before the slip's onset (an estimate);
    # both sensors of a swap until the swap; every other sensor, every frame.
    assert v[:, 0].all()
    assert v[:550, 1].all() and not v[550:, 1].any()
    assert v[:800, 2:].all() and not v[800:, 2:].any()
    # A second slip of the same sensor changes nothing: the first placement is the one kept.
    later = dict(slip, time_s=9.0)
    np.testing.assert_array_equal(contribution_mask(take, [slip, later, swap]), v)
