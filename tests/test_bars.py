"""Long commands show a progress bar (tqdm, on stderr) when a person watches them on a terminal, and stay
quiet when their output goes to a pipe or a file. The commands run as real processes on a real pty;
$FLOCKCAL_PROGRESS_DELAY=0 shows the bars of these short test takes at once (users get them after 2 s)."""

from __future__ import annotations

import fcntl
import os
import pty
import select
import struct
import subprocess
import sys
import termios

import pytest

from flockcal.cli import main
from flockcal.markers import save_markers
from flockcal.simulator import optical
from flockcal.takes import make_take, save_take
from synthetic import articulated


def run_on_terminal(argv: list[str], env: dict, cwd, timeout: float = 120.0) -> tuple[int, str]:
    """`python -m flockcal ARGV` with stdout and stderr on a pty; everything it drew there."""
    master, slave = pty.openpty()
    # A terminal has a size (a bare pty is 0×0, and tqdm draws nothing in no columns): 40 rows, 100 columns.
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 40, 100, 0, 0))
    proc = subprocess.Popen([sys.executable, "-m", "flockcal", *argv], stdin=subprocess.DEVNULL, stdout=slave,
                            stderr=slave, env=env, cwd=cwd)
    os.close(slave)
    out = bytearray()
    while True:
        ready, _, _ = select.select([master], [], [], timeout)
        if not ready:
            proc.kill()
            proc.wait(30)
            os.close(master)
            raise TimeoutError(f"flockcal {' '.join(argv)} said nothing for {timeout} s")
        try:
            chunk = os.read(master, 65536)
        except OSError:  # EIO: the process closed the terminal
            break
        if not chunk:
            break
        out += chunk
    os.close(master)
    return proc.wait(30), out.decode(errors="replace")


def run_piped(argv: list[str], env: dict, cwd) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "flockcal", *argv], capture_output=True, text=True, env=env,
                          cwd=cwd, timeout=120)


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("progress")
    d = articulated(m=5, n=3000, seed=3, joint_types=["root", "ball", "hinge", "ball", "ball"])
    save_take(folder / "take.npz", make_take(d.rotations, d.positions, d.names, d.rate_hz))
    raw = folder / "take.fobraw"
    assert main(["record", "--port", "sim://progress?birds=3&rate=50&motion=walk", "--birds", "3", "-o", str(raw),
                 "--seconds", "1.5"]) == 0
    markers, _ = optical.simulate_markers("linkage", seconds=6, rate_hz=60, seed=2, noise_m=0.001)
    save_markers(folder / "markers.npz", markers)
    return folder


def env(delay: str | None) -> dict:
    out = dict(os.environ)
    out.pop("FLOCKCAL_PROGRESS_DELAY", None)
    if delay is not None:
        out["FLOCKCAL_PROGRESS_DELAY"] = delay
    return out


CASES = [  # (command line, what its bar says)
    (["fit", "take.npz"], "accumulating"),
    (["convert", "take.fobraw", "-o", "converted.npz"], "decoding"),
    (["replay", "take.fobraw"], "decoding"),
    (["report", "take.npz", "-o", "report.html"], "report"),
    (["fit-markers", "markers.npz"], "fit-markers"),
]


@pytest.mark.parametrize("argv, label", CASES, ids=[c[0][0] for c in CASES])
def test_a_terminal_gets_a_progress_bar_and_a_pipe_does_not(files, argv, label):
    rc, screen = run_on_terminal(argv, env("0"), files)
    assert rc == 0, screen[-2000:]
    assert label in screen and "%|" in screen, screen[-2000:]  # tqdm's bar: "label: 40%|####  | 2/5"
    piped = run_piped(argv, env("0"), files)
    assert piped.returncode == 0, piped.stderr
    assert label + ":" not in piped.stderr and "%|" not in piped.stderr


def test_a_quick_command_on_a_terminal_draws_no_bar_before_two_seconds(files):
    # The default delay: a fit of a 30 s take is done well within it.
    rc, screen = run_on_terminal(["fit", "take.npz"], env(None), files)
    assert rc == 0 and "%|" not in screen and "Joints" in screen
