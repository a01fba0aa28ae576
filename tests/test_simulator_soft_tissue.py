"""Promises of the simulator's soft-tissue artefact (STA): each skin sensor's placement on its bone moves
smoothly with the angles of the joints at either end of its segment, up to the set size at the ends of
a range and back when the joints come back; on by default for the human, off for the rigs, recorded
in the truth, settable from the command line and from sim:// URLs."""

from __future__ import annotations

import json

import numpy as np
import pytest
import serial

import flockcal.simulator  # noqa: F401  (registers sim://)
from flockcal.cli import main
from flockcal.simulator.body import SimulatorError, bone_poses
from flockcal.simulator.performer import Performer
from flockcal.simulator.protocol_sim import forget_simulation, get_simulation


def placement_change(sta: Performer, rigid: Performer, times) -> np.ndarray:
    """How far (n, m) each sensor of `sta` sits from where the rigid performer's sensor sits, measured
    in its bone frame: the same body and motion, so the difference is the skin moving, nothing else."""
    R1, t1 = sta.exact_poses(times)
    _, t0 = rigid.exact_poses(times)
    L, root = rigid.motion.at(times)
    B, _ = bone_poses(rigid.model, L, root)
    return np.linalg.norm(np.einsum("nmji,nmj->nmi", B, t1 - t0), axis=-1)


def test_human_sensors_slide_up_to_the_set_size_at_the_ends_of_a_range():
    times = np.arange(0, 60, 0.02)
    sta = Performer(routine="exercise", seed=3, noise=None, seconds=60, sta_mm=15)
    rigid = Performer(routine="exercise", seed=3, noise=None, seconds=60, sta_mm=0)
    moved = placement_change(sta, rigid, times)
    peak = moved.max(axis=0)
    # The inboard joint alone moves a sensor by at most the size, its outboard joints together by at
    # most the size again (a 1e-9 m allowance for rounding).
    assert peak.max() <= 2 * 0.015 + 1e-9
    # The exercise routine takes every joint to the ends of its range: nearly every sensor gets most
    # of the way there (0.6 of the size; the pelvis shares its skin among three outboard joints).
    assert np.mean(peak >= 0.6 * 0.015) >= 0.8
    # Smooth: at 50 Hz the skin never jumps between frames by more than a slip test's margin would.
    assert np.abs(np.diff(moved, axis=0)).max() < 0.002


def test_soft_tissue_comes_back_when_the_joints_come_back():
    perf = Performer(routine="kiosk", seed=2, noise=None, sta_mm=12)
    rigid = Performer(routine="kiosk", seed=2, noise=None, sta_mm=0)
    period = perf.motion.period
    times = np.arange(0, period, 0.05)
    # The kiosk routine loops: one loop later every joint is where it was, and so is every sensor.
    first = placement_change(perf, rigid, times)
    again = placement_change(perf, rigid, times + period)
    assert first.max() > 0.005 and np.abs(first - again).max() < 1e-9
    # At the rest pose the placements are the model's rest placements exactly.
    q = np.broadcast_to(perf.model.rest, (1,) + perf.model.rest.shape)
    S, s = perf.sta.placements(q, perf.model.sensor_offset, perf.model.sensor_rotation)
    np.testing.assert_allclose(s[0], perf.model.sensor_offset, atol=1e-15)
    np.testing.assert_allclose(S[0], perf.model.sensor_rotation, atol=1e-15)


def test_on_by_default_for_the_human_and_never_for_the_rigs():
    assert Performer().sta_mm == 12.0
    assert Performer(model="linkage").sta is None and Performer(model="pair").sta is None
    # The rigs are wood and metal: asking them for skin is a mistake worth saying so.
    with pytest.raises(SimulatorError, match="human model only"):
        Performer(model="linkage", sta_mm=10)
    # Larger than skin moves is refused with the range that makes sense.
    with pytest.raises(SimulatorError, match="0–50 mm"):
        Performer(sta_mm=80)


def test_simulate_records_the_soft_tissue_in_the_truth_and_sta_mm_sets_it(tmp_path, capsys):
    out = tmp_path / "take.npz"
    assert main(["simulate", "--motion", "exercise", "--seconds", "4", "--birds", "6", "--sta-mm", "8",
                 "-o", str(out)]) == 0
    assert "soft tissue 8 mm" in capsys.readouterr().err
    truth = json.loads((tmp_path / "take.truth.json").read_text())
    sta = truth["soft_tissue"]
    assert sta["size_mm"] == 8 and truth["simulation"]["sta_mm"] == 8 and sta["seed"] == 1
    assert set(sta["rms_mm"]) == set(truth["sensors"]) and max(sta["max_mm"].values()) <= 16
    # --sta-mm 0 turns it off: rigid sensors, recorded as such.
    assert main(["simulate", "--seconds", "1", "--birds", "3", "--sta-mm", "0", "-o", str(out)]) == 0
    truth = json.loads((tmp_path / "take.truth.json").read_text())
    assert truth["soft_tissue"] == {"size_mm": 0.0} and truth["simulation"]["sta_mm"] == 0
    # A linkage with skin is refused on the command line as one line.
    assert main(["simulate", "--model", "linkage", "--sta-mm", "5", "-o", str(out)]) == 2
    assert "human model only" in capsys.readouterr().err


def test_sim_urls_take_sta_mm():
    for name, query, size in (("sta-default", "", 12.0), ("sta-off", "&sta_mm=0", 0.0), ("sta-9", "&sta_mm=9", 9.0)):
        port = serial.serial_for_url(f"sim://{name}?birds=4&motion=idle{query}", timeout=0.5)
        try:
            assert get_simulation(name).source.sta_mm == size
        finally:
            port.close()
            forget_simulation(name)
    with pytest.raises(serial.SerialException, match="sta_mm"):
        serial.serial_for_url("sim://sta-bad?birds=4&sta_mm=lots")
