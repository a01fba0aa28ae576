"""What a new user hits at the command line, run as they run it (`flockcal …` in a subprocess): an output
in a folder that does not exist, or a folder given as the output, is one line naming the path and the fix
(exit 2) for every command that writes a file, before any work and with nothing left behind; argument
errors are one line naming the command; `record` stopped by SIGTERM closes its file and says what it wrote.
"""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

import pytest

from flockcal.atomic import OutputError, replacing, write_atomic
from flockcal.drivers.recording import read_recording
from flockcal.markers import save_markers
from flockcal.simulator import optical as so
from service_process import wait_for


def flockcal(*argv, cwd: Path, timeout: float = 120):
    return subprocess.run([sys.executable, "-m", "flockcal", *map(str, argv)], cwd=cwd, capture_output=True,
                          text=True, timeout=timeout)


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> Path:
    """A folder with what the tour makes: a take, a raw recording, a marker take."""
    d = tmp_path_factory.mktemp("inputs")
    run = flockcal("simulate", "--motion", "exercise", "--seconds", "8", "--birds", "4", "--seed", "2",
                   "-o", "take.npz", cwd=d)
    assert run.returncode == 0, run.stderr
    run = flockcal("simulate", "--model", "pair", "--motion", "exercise", "--seconds", "4", "-o", "pair.npz", cwd=d)
    assert run.returncode == 0, run.stderr
    run = flockcal("record", "--port", "sim://outputs?birds=4&motion=exercise&rate=60", "--birds", "4",
                   "--seconds", "1.5", "-o", "rec.fobraw", cwd=d)
    assert run.returncode == 0, run.stderr
    model = so.rods((0.45, 0.50, 0.45), seed=3)
    markers, _ = so.simulate_markers(model, so.rod_motion(model, 10, 60, 3), per_body=(3, 3), noise_m=0.001, seed=3)
    save_markers(d / "markers.npz", markers)
    return d


# Every command that writes a file, with the option that names it (issue #29: six of these printed a
# 15-20 line FileNotFoundError traceback about 'x.part', exit 1, after fitting the whole take).
WRITERS = [
    ("fit", ["take.npz", "--bvh"], "--bvh", "x.bvh"),
    ("export-bvh", ["take.npz", "-o"], "-o", "x.bvh"),
    ("skeleton", ["take.npz", "-o"], "-o", "x.json"),
    ("report", ["take.npz", "-o"], "-o", "x.html"),
    ("convert", ["rec.fobraw", "-o"], "-o", "x.npz"),
    ("fit-markers", ["markers.npz", "--take"], "--take", "x.npz"),
    ("scale", ["pair.npz", "--distance", "0.565", "--apply", "pair.npz", "-o"], "-o", "x.npz"),
    ("simulate", ["--seconds", "2", "-o"], "-o", "x.npz"),
    ("record", ["--port", "sim://outputs?birds=2", "--birds", "2", "--seconds", "1", "-o"], "-o", "x.fobraw"),
    ("fit", ["take.npz", "--gltf"], "--gltf", "x.glb"),
    ("export-gltf", ["take.npz", "-o"], "-o", "x.glb"),
    ("fit", ["take.npz", "--trc"], "--trc", "x.trc"),
]


def _one_line(run, command: str) -> str:
    err = run.stderr
    assert run.returncode == 2, (run.returncode, err)
    assert err.count("\n") == 1 and err.startswith(f"flockcal {command}: error: "), err
    assert "Traceback" not in err
    return err


def _files(folder: Path) -> set[str]:
    return {str(p.relative_to(folder)) for p in folder.rglob("*")}


@pytest.mark.parametrize("command, argv, option, name", WRITERS, ids=[w[0] for w in WRITERS])
def test_an_output_in_a_missing_folder_is_one_line_and_writes_nothing(inputs, command, argv, option, name):
    before = _files(inputs)
    out = inputs / "no-such-folder" / name
    run = flockcal(command, *argv, out, cwd=inputs)
    err = _one_line(run, command)
    assert f"{option} {out}" in err and "does not exist" in err and f"mkdir -p {out.parent}" in err, err
    assert _files(inputs) == before  # no folder made, no .part left, the inputs untouched


@pytest.mark.parametrize("command, argv, option, name", WRITERS[:4], ids=[w[0] for w in WRITERS[:4]])
def test_a_folder_given_as_the_output_is_one_line(inputs, command, argv, option, name, tmp_path):
    run = flockcal(command, *argv, tmp_path, cwd=inputs)
    err = _one_line(run, command)
    assert f"{option} {tmp_path}: that is a folder" in err, err
    assert _files(tmp_path) == set()


def test_a_write_that_fails_names_the_file_and_keeps_the_old_one(tmp_path):
    # Tried: a write that fails half-way (an OSError while writing, as on a full disk) and one that is
    # interrupted (Ctrl-C): the old file keeps its bytes, no .part is left, the error names the file.
    path = tmp_path / "out.bvh"
    write_atomic(path, "old")
    with pytest.raises(OutputError, match=f"cannot write {path}: No space left on device"):
        with replacing(path) as tmp:
            tmp.write_text("half")
            raise OSError(28, "No space left on device")
    with pytest.raises(KeyboardInterrupt):
        with replacing(path) as tmp:
            tmp.write_text("half")
            raise KeyboardInterrupt
    assert path.read_text() == "old" and _files(tmp_path) == {"out.bvh"}


@pytest.mark.parametrize("argv, command, says", [
    # tried: an option fit does not have (it was reported by `flockcal:` after the top-level usage)
    (["fit", "take.npz", "--bogus"], "fit", "unrecognized arguments: --bogus"),
    # tried: a routine simulate does not know (10 lines of usage first)
    (["simulate", "--motion", "run"], "simulate", "invalid choice: 'run'"),
    # tried: fit without its file
    (["fit"], "fit", "the following arguments are required: FILE.npz"),
])
def test_argument_errors_are_one_line_naming_the_command(inputs, argv, command, says):
    run = flockcal(*argv, cwd=inputs)
    err = _one_line(run, command)
    assert says in err and f"flockcal {command} --help" in err, err


def test_record_stopped_by_sigterm_closes_its_file_and_says_what_it_wrote(tmp_path):
    """Tried: `kill` on a running `flockcal record` (what systemd or a supervisor sends): it used to end
    without its "wrote" line. Now it stops as Ctrl-C does: exit 0, the line, a whole recording."""
    err_path = tmp_path / "record.err"
    with open(err_path, "w") as err:
        proc = subprocess.Popen([sys.executable, "-m", "flockcal", "record", "--port",
                                 "sim://sigterm?birds=3&motion=exercise&rate=60", "--birds", "3", "-o", "rec.fobraw"],
                                cwd=tmp_path, stdout=subprocess.DEVNULL, stderr=err)
    try:
        # Recording once it has said so and the file holds data beyond its header.
        def recording() -> bool:
            assert proc.poll() is None, err_path.read_text()
            return ("recording to" in err_path.read_text() and (tmp_path / "rec.fobraw").exists()
                    and (tmp_path / "rec.fobraw").stat().st_size > 4096)

        wait_for(recording, 60, lambda: f"record starts ({err_path.read_text()})")
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=30) == 0, err_path.read_text()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    text = err_path.read_text()
    assert "flockcal record: wrote rec.fobraw:" in text, text
    rec = read_recording(tmp_path / "rec.fobraw")
    assert not rec.truncated and rec.bytes_read > 0
