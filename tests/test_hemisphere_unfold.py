"""Hemisphere flips in recorded takes (issue #50): a take recorded by software that did not track the
hemisphere reads −p wherever a sensor is outside the configured half; `fit`, `convert` and `replay` undo
it (flockcal/hemisphere_unfold.py) and say how many frames they unfolded.

The flipped takes are made here from simulated ones, as the Flock makes them (docs/protocol.md §9, the
manual's rule): the selected axis' sign is forced positive, and the other two signs flip with it — written
out below, not taken from the simulator's or the driver's folding code.
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from flockcal.cli import main
from flockcal.hemisphere_unfold import HemisphereUnfold, unfold_take
from flockcal.simulator.take import simulate
from flockcal.takes import load_take, save_take

AXIS = {"forward": (0, 1.0), "aft": (0, -1.0), "right": (1, 1.0), "left": (1, -1.0), "lower": (2, 1.0), "upper": (2, -1.0)}


def as_the_flock_reports(positions: np.ndarray, hemisphere: str) -> np.ndarray:
    """The selected axis' sign forced positive (toward the hemisphere); where that changed it, the other
    two signs flip too."""
    k, sign = AXIS[hemisphere]
    p = np.array(positions, dtype=float)
    outside = p[..., k] * sign < 0
    p[..., k] = sign * np.abs(p[..., k])
    others = [i for i in range(3) if i != k]
    p[..., others] = np.where(outside[..., None], -p[..., others], p[..., others])
    return p


@pytest.fixture(scope="module")
def walk(tmp_path_factory):
    """A 16-sensor walk, 20 s at 60 Hz, rigid sensors (fit quickly, no slip to find), some dropouts."""
    take, _ = simulate("human", "walk", seconds=20, rate_hz=60, seed=2, sta_mm=0, faults={"dropout": 0.01})
    d = tmp_path_factory.mktemp("flips")
    save_take(d / "plain.npz", take)
    return d, take


def _fit(path, capsys) -> tuple[dict, str]:
    assert main(["fit", str(path), "--json", "--no-slips"]) == 0
    got = capsys.readouterr()
    return json.loads(got.out), got.err


@pytest.mark.parametrize("hemisphere", ["lower", "left"])
def test_a_take_with_hemisphere_flips_fits_as_the_unflipped_take_does(walk, tmp_path, capsys, hemisphere):
    # Lower: the transmitter sits at hip height, so chest, head and arms read mirrored from the first frame
    # and the legs and hands cross; left: the body straddles the boundary plane, its midline sensors
    # crossing all the time. Fitted as read, 8 and 5 of the 15 tree edges were wrong and centres 468 and
    # 768 mm off.
    d, take = walk
    flipped = as_the_flock_reports(take.positions, hemisphere)
    mirrored = (flipped != take.positions).any(axis=2) & take.valid
    assert 0.1 < mirrored.mean() < 0.9  # some sensors flipped, some not: crossings, not a mirrored take
    save_take(tmp_path / "flipped.npz", dataclasses.replace(take, positions=flipped))
    want, _ = _fit(d / "plain.npz", capsys)
    got, err = _fit(tmp_path / "flipped.npz", capsys)
    # The target is the tree and every centre within 5 mm; the positions come back exactly, so the
    # whole JSON does.
    assert got == want
    frames = int(mirrored.any(axis=1).sum())
    assert f"unfolded hemisphere flips in {frames} frame(s)" in err and err.count("\n") == 1


def test_unfolding_a_chunk_at_a_time_gives_the_whole_take_unfolded(walk):
    # Streamed takes: state carries across chunks (a sensor's last position and its sign); chunks as small
    # as 7 frames (the live reader's batches at 144 Hz) decide as the whole take does here.
    _, take = walk
    flipped = as_the_flock_reports(take.positions, "lower")
    for size in (7, 500, take.n_frames):
        u = HemisphereUnfold(take.n_sensors)
        out = np.concatenate([u.feed(take.times[a:a + size], flipped[a:a + size], take.valid[a:a + size])
                              for a in range(0, take.n_frames, size)])
        np.testing.assert_array_equal(out[take.valid], take.positions[take.valid], err_msg=f"chunks of {size}")


def test_a_sensor_unseen_while_it_crossed_is_placed_again_by_its_neighbours():
    # Half-second dropout bursts: a hand can cross the boundary while it is lost, so its path says nothing
    # across the gap; the distances to the other sensors place it again.
    take, _ = simulate("human", "kiosk", seconds=20, rate_hz=60, seed=5, sta_mm=0,
                       faults={"dropout": 0.02, "dropout_burst_s": 0.5})
    flipped = as_the_flock_reports(take.positions, "lower")
    got, how = unfold_take(dataclasses.replace(take, positions=flipped))
    np.testing.assert_array_equal(got.positions[take.valid], take.positions[take.valid])
    assert how.frames_unfolded > 0


def test_a_take_without_flips_is_left_as_it_is(walk):
    # Nothing to unfold: the same Take object back, so `fit --json` stays byte for byte what it was
    # (tests/golden/calibration holds that), and nothing is said.
    _, take = walk
    got, how = unfold_take(take)
    assert got is take and how.frames_unfolded == 0 and how.summary(take.names) is None


def test_a_recording_begun_with_most_sensors_outside_reads_right_from_the_reader(tmp_path, capsys):
    # Recorded in "lower" with the transmitter at hip height, the simulated performer's chest, head and arms
    # start outside (read as -p) and the legs inside: most birds read mirrored from the connection's first
    # frame. The reader places them by the take's own rule (the performer in front of the transmitter), not
    # by what most birds read: placing each by the others' median (the rule before) turned the legs to
    # match the mirrored majority, a performer mirrored whole that `replay` and `convert` then had no flip
    # to undo (CI, 2026-12-07). The simulated performer stands in front of the transmitter (x > 0.2 m for
    # every sensor, simulator/body.py); mirrored ones read x < 0.
    raw, npz = tmp_path / "take.fobraw", tmp_path / "take.npz"
    assert main(["record", "--port", "sim://flips-convert?birds=16&rate=50&motion=walk", "--birds", "16",
                 "--rate", "50", "--hemisphere", "lower", "--scale", "72", "-o", str(raw), "--seconds", "1.5"]) == 0
    capsys.readouterr()
    assert main(["replay", str(raw)]) == 0
    assert "no hemisphere flips left to unfold" in capsys.readouterr().out
    assert main(["convert", str(raw), "-o", str(npz)]) == 0
    assert "unfolded" not in capsys.readouterr().err
    take = load_take(npz)
    x = take.positions[..., 0][take.valid]
    assert len(x) > 0 and (x > 0.2).all(), x.min()


def test_the_python_api_unfolds_as_the_command_does(walk):
    # flockcal.fit(take) is `flockcal fit`'s path: the same unfolding, said as a warning.
    import flockcal

    _, take = walk
    flipped = dataclasses.replace(take, positions=as_the_flock_reports(take.positions, "lower"))
    with pytest.warns(UserWarning, match="unfolded hemisphere flips in"):
        got = flockcal.fit(flipped, slips=False).to_dict()
    assert got == flockcal.fit(take, slips=False).to_dict()


def test_the_live_driver_places_a_bird_that_began_across_the_boundary_by_the_other_sensors():
    # A service (re)started while the performer moves: the right hand's first record comes from behind the
    # forward hemisphere (reported as −p), and every toggle after it would keep it mirrored for the session.
    from flockcal.drivers.checks import BirdChecks
    from flockcal.drivers.hemispheres import fold_to_hemisphere
    from flockcal.drivers.link import FlockSetup

    rng = np.random.default_rng(3)
    m, n = 8, 40
    centre = np.array([0.3, 1.2, 0.0])  # the performer beside the transmitter, the x = 0 plane near them
    true = centre + rng.uniform(-0.25, 0.25, (m, 3)) + 0.002 * np.arange(n)[:, None, None]
    true[:, 5] = np.array([-0.05, 1.3, 0.1]) + np.column_stack([np.linspace(0, 0.2, n), np.zeros(n), np.zeros(n)])
    assert true[0, 5, 0] < 0 < true[-1, 5, 0]  # it begins behind the plane and crosses into the hemisphere
    reported = fold_to_hemisphere(true, "forward")
    setup = FlockSetup(urls=[], birds=m, addresses=list(range(1, m + 1)), group=True, mode="stream",
                       record_format="position_matrix", scale_inches=72, rate_hz=144.0, hemisphere="forward",
                       baud=115200)
    events = []
    checks = BirdChecks(setup, events.append)
    times = np.arange(n) / 144.0
    R = np.broadcast_to(np.eye(3), (n, m, 3, 3)).copy()
    valid = np.ones((n, m), bool)
    p = reported.copy()
    for a in range(0, n, 3):  # the reader's small hand-overs
        s = slice(a, a + 3)
        checks.apply(times[s], R[s], p[s], valid[s], np.repeat(times[s, None], m, axis=1), None)
    np.testing.assert_allclose(p, true, atol=1e-12)
    assert any("began across the hemisphere boundary" in e[1] for e in events), events
    # The same frames fed from a moment the hand is in front: nothing to place, nothing changed.
    later = BirdChecks(setup, events.append)
    q = reported[30:].copy()
    later.apply(times[30:], R[30:], q, valid[30:], np.repeat(times[30:, None], m, axis=1), None)
    np.testing.assert_allclose(q, true[30:], atol=1e-12)
