"""A take too short or too still to fit gets a one-line warning and exit code 3 from every command that
fits one (fit, report, export-bvh, skeleton), and nothing is written; --allow-partial fits it anyway
(the warning stays, the exit code is 0). A take that moves is fitted without a word."""

from __future__ import annotations

import pytest

from flockcal.cli import main
from flockcal.takes import make_take, save_take
from synthetic import articulated


def _save(tmp_path, name, d, frames=None):
    sl = slice(None) if frames is None else slice(0, frames)
    path = tmp_path / name
    save_take(path, make_take(d.rotations[sl], d.positions[sl], d.names, d.rate_hz))
    return path


@pytest.fixture(scope="module")
def takes(tmp_path_factory):
    folder = tmp_path_factory.mktemp("takecheck")
    moving = articulated(m=4, n=400, seed=7, joint_types=["root", "ball", "ball", "hinge"])
    # Every body rigidly fixed to the root: the sensors move together and no joint turns.
    still = articulated(m=4, n=400, seed=7, joint_types=["root", "rigid", "rigid", "rigid"])
    return {"moving": _save(folder, "moving.npz", moving), "still": _save(folder, "still.npz", still),
            "two_frames": _save(folder, "two.npz", moving, frames=2)}


def _run(capsys, *argv):
    rc = main([*map(str, argv)])
    out, err = capsys.readouterr()
    return rc, out, err


@pytest.mark.parametrize("which, problem", [("two_frames", "too short to fit: 2 frame(s)"),
                                            ("still", "too still to fit")])
def test_fit_warns_in_one_line_and_exits_3(takes, capsys, which, problem):
    # Tried: a 2-frame take (the case) and a take whose sensors never turn relative to each other.
    rc, out, err = _run(capsys, "fit", takes[which])
    assert rc == 3 and out == ""
    assert err.count("\n") == 1 and problem in err and "--allow-partial" in err


@pytest.mark.parametrize("which", ["two_frames", "still"])
def test_allow_partial_fits_it_anyway_with_the_warning(takes, capsys, which):
    rc, out, err = _run(capsys, "fit", takes[which], "--json", "--allow-partial")
    assert rc == 0 and out.startswith("{")
    assert err.count("\n") == 1 and "fitting it anyway (--allow-partial)" in err


@pytest.mark.parametrize("command, suffix", [("report", "html"), ("export-bvh", "bvh"), ("export-gltf", "glb"),
                                             ("skeleton", "json")])
def test_output_commands_write_nothing_for_a_still_take(takes, tmp_path, capsys, command, suffix):
    out = tmp_path / f"out.{suffix}"
    rc, _, err = _run(capsys, command, takes["still"], "-o", out)
    assert rc == 3 and "too still to fit" in err and err.count("\n") == 1
    assert not out.exists()


def test_a_take_that_moves_fits_without_a_warning(takes, capsys):
    rc, out, err = _run(capsys, "fit", takes["moving"])
    assert rc == 0 and "Joints" in out and "warning" not in err
