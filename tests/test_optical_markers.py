"""Marker takes in and out: the marker .npz of design.md §5, C3D through ezc3d, and `flockcal fit-markers`."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from flockcal.cli import main
from flockcal.markers import MarkerError, load_markers, make_marker_take, save_markers
from flockcal.simulator import optical as so
from real_captures import capture_path


@pytest.fixture(scope="module")
def rod_take():
    model = so.rods((0.45, 0.50, 0.45), seed=3)
    take, truth = so.simulate_markers(model, so.rod_motion(model, 10, 60, 3), per_body=(3, 3), noise_m=0.001, seed=3, occlusion=0.02)
    return take, truth


def write_c3d(path: Path, take, units="mm"):
    """The take as a C3D file; the calling test skips, saying why, without the optical extra."""
    ezc3d = pytest.importorskip("ezc3d", reason="writing C3D needs ezc3d: pip install '.[optical]' (or '.[test]')")

    c = ezc3d.c3d()
    scale = {"mm": 1000.0, "m": 1.0}[units]
    c["parameters"]["POINT"]["RATE"]["value"] = [take.rate_hz]
    c["parameters"]["POINT"]["LABELS"]["value"] = list(take.marker_names)
    pts = np.ones((4, take.n_markers, take.n_frames))
    pts[:3] = take.markers.transpose(2, 1, 0) * scale
    c["data"]["points"] = pts
    c.add_parameter("POINT", "UNITS", [units])
    c.write(str(path))


def test_marker_npz_round_trip_keeps_gaps(tmp_path, rod_take):
    take, _ = rod_take
    save_markers(tmp_path / "t.npz", take)
    back = load_markers(tmp_path / "t.npz")
    assert back.marker_names == take.marker_names
    np.testing.assert_array_equal(np.isnan(back.markers), np.isnan(take.markers))
    np.testing.assert_allclose(back.markers, take.markers, equal_nan=True)


def test_c3d_written_by_ezc3d_loads_in_metres_with_gaps(tmp_path, rod_take):
    take, _ = rod_take
    write_c3d(tmp_path / "t.c3d", take)
    back = load_markers(tmp_path / "t.c3d")
    assert back.marker_names == take.marker_names
    assert back.rate_hz == pytest.approx(take.rate_hz)
    np.testing.assert_array_equal(np.isnan(back.markers).any(-1), np.isnan(take.markers).any(-1))
    np.testing.assert_allclose(back.markers, take.markers, atol=1e-5, equal_nan=True)  # C3D stores float32


@pytest.mark.parametrize(
    "arrays, message",
    [
        # tried: markers with only two coordinates
        ({"markers": np.zeros((5, 2, 2)), "marker_names": ["a", "b"], "rate_hz": 60.0}, "shape"),
        # tried: millimetres where metres are expected
        ({"markers": np.full((5, 2, 3), 1500.0), "marker_names": ["a", "b"], "rate_hz": 60.0}, "not metres"),
        # tried: a repeated marker name
        ({"markers": np.zeros((5, 2, 3)), "marker_names": ["a", "a"], "rate_hz": 60.0}, "unique"),
        # tried: a negative frame rate
        ({"markers": np.zeros((5, 2, 3)), "marker_names": ["a", "b"], "rate_hz": -1.0}, "rate_hz"),
        # tried: fewer names than markers
        ({"markers": np.zeros((5, 3, 3)), "marker_names": ["a", "b"], "rate_hz": 60.0}, "marker_names"),
    ],
)
def test_bad_marker_arrays_get_one_clear_error(arrays, message):
    with pytest.raises(MarkerError, match=message):
        make_marker_take(arrays["markers"], arrays["marker_names"], arrays["rate_hz"])


def test_bad_files_are_named_with_the_fix(tmp_path):
    # tried: a missing file, a sensor take given to the marker loader, a .txt (a bad .c3d: below)
    with pytest.raises(MarkerError, match="no such file"):
        load_markers(tmp_path / "nope.npz")
    np.savez(tmp_path / "sensors.npz", rotations=np.zeros((2, 2, 3, 3)), positions=np.zeros((2, 2, 3)))
    with pytest.raises(MarkerError, match="flockcal fit"):
        load_markers(tmp_path / "sensors.npz")
    (tmp_path / "x.txt").write_text("")
    with pytest.raises(MarkerError, match="unknown marker file type"):
        load_markers(tmp_path / "x.txt")


def test_a_text_file_named_c3d_is_not_a_readable_c3d(tmp_path):
    pytest.importorskip("ezc3d", reason="reading C3D needs ezc3d: pip install '.[optical]' (or '.[test]')")
    (tmp_path / "bad.c3d").write_text("not a c3d")
    with pytest.raises(MarkerError, match="not a readable C3D"):
        load_markers(tmp_path / "bad.c3d")


def test_without_the_optical_extra_a_c3d_gets_one_line_naming_it(tmp_path, capsys, monkeypatch):
    # Tried: fit-markers on a C3D file where ezc3d is not installed (as after the README's `pip install .`):
    # one line naming the extra, exit 2, in either environment (ezc3d hidden when it is installed).
    monkeypatch.setitem(sys.modules, "ezc3d", None)
    (tmp_path / "take.c3d").write_bytes(b"\x02\x50" + bytes(510))
    assert main(["fit-markers", str(tmp_path / "take.c3d")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "[optical]" in err and "ezc3d" in err, err


def test_fit_markers_json_matches_the_fit_shape_plus_bodies(tmp_path, rod_take, capsys):
    take, truth = rod_take
    write_c3d(tmp_path / "rods.c3d", take)
    assert main(["fit-markers", str(tmp_path / "rods.c3d"), "--json", "--take", str(tmp_path / "poses.npz")]) == 0
    out = json.loads(capsys.readouterr().out)
    assert {frozenset(e) for e in out["parent"].items()} == {frozenset(e) for e in truth["parent"].items()}
    assert sorted(m for ms in out["bodies"].values() for m in ms) == sorted(take.marker_names)
    assert {"sensors", "root", "joints", "bones", "loop_candidates", "slip_events"} <= set(out)
    from flockcal.takes import load_take

    poses = load_take(tmp_path / "poses.npz")
    assert poses.names == tuple(out["sensors"]) and poses.n_frames == take.n_frames


def test_fit_markers_on_a_bad_file_prints_one_line_and_exits_2(tmp_path):
    # tried: a file that does not exist, through the real command line
    proc = subprocess.run(
        [sys.executable, "-m", "flockcal", "fit-markers", str(tmp_path / "missing.c3d")], capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 2
    assert proc.stderr.strip().count("\n") == 0 and "no such file" in proc.stderr


def test_a_real_c3d_with_analog_channels_only_is_read_and_refused_clearly(tmp_path):
    """Tried: a real capture's own analog channels (38 channels, 11,600 samples of the pyomeca file)
    written back with its 51 markers removed — what a force-plate or EMG-only export looks like. flockcal
    must read it and say there is nothing to fit, not crash. (No network: the file is made from the
    shared capture, and the test skips with a reason where ../shared/data is absent.)"""
    ezc3d = pytest.importorskip("ezc3d", reason="reading C3D needs ezc3d: pip install '.[optical]' (or '.[test]')")
    c3d = ezc3d.c3d(str(capture_path("pyomeca_markers_analogs.c3d")))
    n = c3d["data"]["points"].shape[2]
    c3d["data"]["points"] = np.zeros((4, 0, n))
    for key in ("LABELS", "DESCRIPTIONS"):
        c3d["parameters"]["POINT"][key]["value"] = []
    c3d["parameters"]["POINT"]["USED"]["value"] = [0]
    del c3d["data"]["meta_points"]
    c3d.write(str(tmp_path / "analogs.c3d"))
    assert ezc3d.c3d(str(tmp_path / "analogs.c3d"))["data"]["analogs"].shape[1] == 38  # the analogs stayed
    with pytest.raises(MarkerError, match="holds no 3D points"):
        load_markers(tmp_path / "analogs.c3d")
    proc = subprocess.run([sys.executable, "-m", "flockcal", "fit-markers", str(tmp_path / "analogs.c3d")],
                          capture_output=True, text=True, timeout=120)  # fmt: skip
    assert proc.returncode == 2 and "holds no 3D points" in proc.stderr and "Traceback" not in proc.stderr

def _fit_markers(*argv, cwd):
    return subprocess.run([sys.executable, "-m", "flockcal", "fit-markers", *map(str, argv)], cwd=cwd,
                          capture_output=True, text=True, timeout=120)


def test_a_c3d_cut_short_is_refused_with_the_frames_it_holds_unless_salvaged(tmp_path):
    """Tried: the first 100 kB of the real knee trial (a copy cut short), as issue #29 did: it was fitted
    without a word (exit 0, 40 of 922 frames, other bodies). Now it is refused with the count it holds and
    the way to fit it anyway; with --salvage it is fitted with a warning. The counts come from ezc3d's
    own reading of the whole file and of the cut one."""
    knee = capture_path("biobuddy_right_knee.c3d")  # skips, saying why, without the capture or ezc3d
    import ezc3d

    whole = ezc3d.c3d(str(knee))["data"]["points"].shape[2]
    (tmp_path / "cut.c3d").write_bytes(knee.read_bytes()[:100_000])
    held = ezc3d.c3d(str(tmp_path / "cut.c3d"))["data"]["points"].shape[2]
    assert 2 <= held < whole  # the cut left some frames: what the message must count

    run = _fit_markers("cut.c3d", "--json", cwd=tmp_path)
    assert run.returncode == 2 and run.stdout == "" and run.stderr.count("\n") == 1, run.stderr
    assert run.stderr.startswith("flockcal fit-markers: error: cut.c3d: the file ends early")
    assert f"holds {held} of the {whole} frames" in run.stderr and "--salvage" in run.stderr, run.stderr

    run = _fit_markers("cut.c3d", "--salvage", cwd=tmp_path)
    assert run.returncode == 0, run.stderr
    assert f"fitted the {held} frames it holds of the {whole}" in run.stderr and "warning" in run.stderr
    assert f"{held} frames at 100 Hz" in run.stdout.splitlines()[0]

    # Cut inside its parameter section (before any frame): one line saying so, even with --salvage.
    (tmp_path / "head.c3d").write_bytes(knee.read_bytes()[:5000])
    for extra in ([], ["--salvage"]):
        run = _fit_markers("head.c3d", *extra, cwd=tmp_path)
        assert run.returncode == 2 and run.stderr.count("\n") == 1, run.stderr
        assert "ends at byte 5000, before its marker data" in run.stderr and "copy it again" in run.stderr
    # The whole file is not flagged.
    assert load_markers(knee).declared_frames is None and load_markers(knee).n_frames == whole


def test_the_knee_table_says_it_has_no_bones_instead_of_an_empty_heading(tmp_path):
    # Tried: the knee trial's table, whose tree is one joint (thigh-shank): it printed "bones:" and nothing.
    run = _fit_markers(capture_path("biobuddy_right_knee.c3d"), cwd=tmp_path)
    assert run.returncode == 0, run.stderr
    lines = run.stdout.splitlines()
    bones = [k for k, line in enumerate(lines) if line.startswith("bones:")]
    assert len(bones) == 1 and lines[bones[0]].startswith("bones: none"), run.stdout


def test_fit_markers_into_a_pipe_imports_neither_scipy_spatial_nor_tqdm(tmp_path, rod_take):
    # The CLI's start-up (docs/optical.md, issue 31 speed): `flockcal fit-markers --json` with its output
    # piped, in a fresh interpreter, fits and prints without importing scipy.spatial (Rotation is imported
    # by the functions that need it) or tqdm (no bar may be drawn into a pipe). What was tried: the whole
    # command through the CLI's main, then the modules left in sys.modules.
    path = tmp_path / "rods.npz"
    save_markers(path, rod_take[0])
    code = ("import io, json, sys, contextlib\n"
            "from flockcal.cli import main\n"
            "buf = io.StringIO()\n"
            "with contextlib.redirect_stdout(buf):\n"
            f"    rc = main(['fit-markers', {str(path)!r}, '--json'])\n"
            "print(rc, len(json.loads(buf.getvalue())['bodies']),\n"
            "      sorted(m for m in sys.modules if m in ('scipy.spatial', 'tqdm')))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "0 3 []", out.stdout
