"""`flockcal report` draws a take with the up axis its file states (issue 50 item 5): a C3D's own (+z, the
format's convention, unless its POINT:Z_SCREEN names another), a marker .npz's 'up' entry, the Flock's -z for
sensor takes, `--up` over all of them; and the page says which and why."""

import html
from pathlib import Path

import numpy as np
import pytest

from flockcal.cli import main
from flockcal.exports.bvh import bvh_world
from flockcal.markers import load_markers, make_marker_take, save_c3d, save_markers
from flockcal.simulator import optical as so

# The simulator's world is the Flock's, z down; turning it half a turn about x makes it z up, as a lab's C3D is.
Z_DOWN_TO_Z_UP = np.diag([1.0, -1.0, -1.0])


@pytest.fixture(scope="module")
def walk():
    """A short simulated walk of fixed markers, in the simulator's z-down world."""
    take, _ = so.simulate_markers("human", "walk", seconds=4.0, rate_hz=60.0, seed=2, per_body=(3, 3), noise_m=0.001)
    return take


def write_c3d(path: Path, markers: np.ndarray, take, z_screen: str | None = None) -> None:
    ezc3d = pytest.importorskip("ezc3d", reason="writing C3D needs ezc3d: pip install '.[optical]' (or '.[test]')")
    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [take.rate_hz]
    c["parameters"]["POINT"]["LABELS"]["value"] = list(take.marker_names)
    pts = np.ones((4, take.n_markers, take.n_frames))
    pts[:3] = markers.transpose(2, 1, 0) * 1000.0
    c["data"]["points"] = pts
    c.add_parameter("POINT", "UNITS", ["mm"])
    if z_screen is not None:
        c.add_parameter("POINT", "Z_SCREEN", [z_screen])
    c.write(str(path))


def head_above_feet(markers: np.ndarray, names, up: str) -> bool:
    """The test's own judgement: the head's markers above the feet's, along the page's up (bvh_world's y)."""
    height = (markers @ bvh_world(up).T)[..., 1]
    head = [i for i, n in enumerate(names) if n.startswith("head")]
    feet = [i for i, n in enumerate(names) if "foot" in n]
    return bool(np.nanmean(height[:, head]) > np.nanmean(height[:, feet]) + 1.0)


def drawn_with(html_path: Path) -> str:
    text = html.unescape(html_path.read_text())
    start = text.index("Drawn with ")
    return text[start:text.index("</p>", start)]


def test_a_c3d_is_drawn_z_up_by_its_own_convention_and_the_page_says_so(tmp_path, walk):
    markers = walk.markers @ Z_DOWN_TO_Z_UP.T
    write_c3d(tmp_path / "walk.c3d", markers, walk)
    assert main(["report", str(tmp_path / "walk.c3d"), "-o", str(tmp_path / "r.html")]) == 0
    said = drawn_with(tmp_path / "r.html")
    assert said.startswith("Drawn with +z up: the C3D convention"), said
    assert head_above_feet(markers, walk.marker_names, "+z")
    assert not head_above_feet(markers, walk.marker_names, "-z"), "the old default drew this take upside down"


def test_a_c3d_whose_z_screen_says_y_is_drawn_y_up(tmp_path, walk):
    z_up_to_y_up = np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])  # +z → +y
    markers = walk.markers @ Z_DOWN_TO_Z_UP.T @ z_up_to_y_up.T
    write_c3d(tmp_path / "walk.c3d", markers, walk, z_screen="+Y")
    assert load_markers(tmp_path / "walk.c3d").up == "+y"
    assert main(["report", str(tmp_path / "walk.c3d"), "-o", str(tmp_path / "r.html")]) == 0
    assert drawn_with(tmp_path / "r.html").startswith("Drawn with +y up: the C3D's POINT:Z_SCREEN")
    assert head_above_feet(markers, walk.marker_names, "+y")


def test_up_given_on_the_command_line_wins_over_the_file(tmp_path, walk):
    write_c3d(tmp_path / "walk.c3d", walk.markers @ Z_DOWN_TO_Z_UP.T, walk)
    assert main(["report", str(tmp_path / "walk.c3d"), "-o", str(tmp_path / "r.html"), "--up=-z"]) == 0
    assert drawn_with(tmp_path / "r.html") == "Drawn with -z up: --up."


def test_flockcals_own_c3d_states_its_z_down_world_and_is_drawn_head_up(tmp_path, walk):
    # `flockcal simulate -o take.c3d` writes the simulator's z-down world: without POINT:Z_SCREEN a reader
    # takes the C3D convention, +z, and draws it upside down.
    pytest.importorskip("ezc3d", reason="writing C3D needs ezc3d: pip install '.[optical]' (or '.[test]')")
    save_c3d(tmp_path / "sim.c3d", walk)
    assert load_markers(tmp_path / "sim.c3d").up == "-z"
    assert main(["report", str(tmp_path / "sim.c3d"), "-o", str(tmp_path / "r.html")]) == 0
    assert drawn_with(tmp_path / "r.html") == "Drawn with -z up: the C3D's POINT:Z_SCREEN."
    assert head_above_feet(walk.markers, walk.marker_names, "-z")


def test_a_marker_npz_keeps_its_up_entry_and_one_without_is_drawn_in_the_flocks_frame(tmp_path, walk):
    save_markers(tmp_path / "sim.npz", walk)  # the simulator's take says it is z down
    assert load_markers(tmp_path / "sim.npz").up == "-z"
    assert main(["report", str(tmp_path / "sim.npz"), "-o", str(tmp_path / "a.html")]) == 0
    assert drawn_with(tmp_path / "a.html") == "Drawn with -z up: the file's 'up' entry."
    assert head_above_feet(walk.markers, walk.marker_names, "-z")
    plain = make_marker_take(walk.markers, walk.marker_names, walk.rate_hz)
    save_markers(tmp_path / "plain.npz", plain)
    assert load_markers(tmp_path / "plain.npz").up is None
    assert main(["report", str(tmp_path / "plain.npz"), "-o", str(tmp_path / "b.html")]) == 0
    assert drawn_with(tmp_path / "b.html").startswith("Drawn with -z up: the Flock's transmitter frame")


def test_a_marker_npz_with_an_up_flockcal_cannot_draw_is_refused_in_one_line(tmp_path, walk):
    np.savez(tmp_path / "bad.npz", markers=walk.markers, marker_names=np.array(walk.marker_names),
             rate_hz=walk.rate_hz, up="sideways")
    with pytest.raises(Exception, match=r"'up' must be one of \+z, -z, \+y, got 'sideways'"):
        load_markers(tmp_path / "bad.npz")
