"""The driver asks the tracker what it is (EXAMINE p15 model, p0 status, p3 position scaling) and uses
the answers; the fake flock answers them as the hardware does (each bird keeps its own scale); `record`
reports the frame rate it actually got and names the cause and fix when it is short of the asked rate."""

from __future__ import annotations

import os
import re

import numpy as np
import pytest

from flockcal.cli import main
from flockcal.drivers.commands import fbb_prefix
from flockcal.drivers.parameters import change_command, examine_command
from flockcal.drivers.records import FORMATS, decode_records
from flockcal.drivers.status import decode_status_word
from flockcal.rotations import from_euler
from flockcal.drivers.link import Timing, TrackerError
from flockcal.drivers.reader import TrackerConfig, TrackerReader
from flockcal.clock import ManualClock
from flockcal.simulator.fake_tracker import FakeFlock
from flockcal.simulator.smooth_source import SmoothSource
from flockcal.simulator.pty_tracker import PtyTracker
from service_process import wait_for


def _ask(flock, clock, data, dt=0.05):
    flock.write(data)
    clock.advance(dt)
    return flock.read()


def test_fake_answers_model_status_and_per_bird_scale_as_the_hardware_does():
    clock = ManualClock()
    flock = FakeFlock(SmoothSource(3), clock=clock, scale_inches=36.0)
    # Model ID (p15): 10 bytes of space-padded ASCII, as the Flock manual gives it.
    assert _ask(flock, clock, examine_command(15)) == b"6DFOB     "
    # Status word: master bit only on address 1; the format bits follow a format command.
    master = decode_status_word(_ask(flock, clock, examine_command(0)))
    assert master.master and master.running and master.format == FORMATS["position_angles"]
    slave = decode_status_word(_ask(flock, clock, fbb_prefix(2, "normal") + examine_command(0)))
    assert not slave.master
    _ask(flock, clock, change_command(50, 3))
    _ask(flock, clock, fbb_prefix(2, "normal") + bytes([FORMATS["position_matrix"].command]))
    slave = decode_status_word(_ask(flock, clock, fbb_prefix(2, "normal") + examine_command(0)))
    assert slave.format == FORMATS["position_matrix"] and slave.initialised
    # Position scaling is each bird's own: changing bird 2 leaves birds 1 and 3 at 36 in.
    _ask(flock, clock, fbb_prefix(2, "normal") + change_command(3, bytes([1, 0])))
    scales = [_ask(flock, clock, fbb_prefix(a, "normal") + examine_command(3)) for a in (1, 2, 3)]
    assert scales == [b"\x00\x00", b"\x01\x00", b"\x00\x00"]


def test_fake_encodes_each_birds_records_at_its_own_scale():
    class Far(SmoothSource):
        def poses(self, times):
            r, p, v = super().poses(times)
            return r, p * 0 + [1.2, 0.1, 0.3], v  # 1.2 m: beyond 36 in (0.914 m), inside 72 in

    clock = ManualClock()
    flock = FakeFlock(Far(2), clock=clock, scale_inches=36.0)
    _ask(flock, clock, change_command(50, 2) + change_command(35, 1))
    _ask(flock, clock, fbb_prefix(2, "normal") + change_command(3, bytes([1, 0])))
    records = np.frombuffer(_ask(flock, clock, b"B"), np.uint8).reshape(2, -1)
    _, p1, _ = decode_records("position_angles", records[0].tobytes(), group=True, scale_inches=36.0)
    _, p2, _ = decode_records("position_angles", records[1].tobytes(), group=True, scale_inches=72.0)
    assert p1[0, 0] == pytest.approx(36 * 0.0254, abs=2e-4)  # bird 1 clips at its 36 in
    assert p2[0, 0] == pytest.approx(1.2, abs=3e-4)  # bird 2 reads it at 72 in


class Reach:
    """Four sensors; sensor 1 swings out to 1.1 m (beyond the 36-inch full scale) and back."""

    n_sensors = 4
    names = ("s0", "s1", "s2", "s3")

    def __init__(self, power_up_scale: float):
        self.full_scale_in = power_up_scale

    def poses(self, times):
        t = np.asarray(times, float)
        p = np.zeros((len(t), 4, 3))
        p[:, :, 0] = 0.3 + 0.1 * np.arange(4)
        p[:, :, 2] = 0.1
        p[:, 1, 0] = 0.75 + 0.35 * np.sin(2 * np.pi * 0.8 * t)
        R = from_euler(0.3 * np.sin(t)[:, None] + np.zeros((1, 4)), np.zeros((len(t), 4)),
                                    np.zeros((len(t), 4)))
        return R, p, np.ones((len(t), 4), bool)


@pytest.mark.parametrize("power_up", [72.0, 36.0])
def test_without_a_scale_the_driver_keeps_the_trackers_own(power_up):
    valid, events = [], []
    with PtyTracker(Reach(power_up), birds=4, baud=115200) as trk:
        cfg = TrackerConfig(urls=[trk.device], birds=4, rate_hz=60, record_format="position_quaternion",
                            scale_inches=None, timing=Timing.fast())
        reader = TrackerReader(cfg, on_frames=lambda f: valid.append(f.valid.copy()), on_event=events.append)
        reader.start(wait=15)
        # 1.5 s of the tracker's frames (90 at 60 Hz), counted: a starved machine reads them later.
        wait_for(lambda: sum(map(len, valid)) >= 90, 60, "90 frames read")
        reader.stop()
        flock_scale = trk.flock.scale_inches
    assert reader.setup.scale_from_tracker and reader.setup.scale_inches == power_up == flock_scale
    assert reader.setup.model == "6DFOB" and reader.status().model == "6DFOB"
    connected = next(e for e in events if e.kind == "connected")
    assert f"{power_up:g}-inch scale (as the tracker was set)" in connected.message
    saturated = reader.status().saturated_records
    if power_up == 72.0:  # the reach fits the tracker's scale: nothing clipped
        assert saturated == 0 and np.concatenate(valid)[1:-1].all()
    else:  # kept at 36 in, the reach clips and the operator is told the fix
        assert saturated > 0 and any(e.kind == "position_saturated" and "--scale 72" in e.message for e in events)


def test_an_extended_range_controller_is_refused_by_its_model_id():
    # Tried: a flock whose master is an ERC (model 6DERC, no sensor of its own).
    with PtyTracker(SmoothSource(2), birds=2, ert=True, baud=115200) as trk:
        reader = TrackerReader(TrackerConfig(urls=[trk.device], birds=2, timing=Timing.fast()))
        with pytest.raises(TrackerError) as err:
            reader.start(wait=10)
    assert "extended range controller (model 6DERC)" in str(err.value)


def _record(capsys, argv) -> str:
    assert main(["record", *argv]) == 0
    return capsys.readouterr().err


def test_record_on_a_line_slower_than_baud_says_reports_the_rate_it_got_and_the_fix(tmp_path, capsys):
    # Tried (the case): --baud 921600 against a line that really runs at 115200. The driver
    # plans position/matrix (6 × 25 B at 100 Hz = 15,000 B/s), the line carries 11,520 B/s, so each set
    # takes 13 ms and the bird skips every other 10 ms cycle: 50 frames/s.
    with PtyTracker(SmoothSource(6), birds=6, baud=115200, rate_hz=100.0) as trk:
        err = _record(capsys, ["--port", trk.device, "--birds", "6", "--baud", "921600", "--seconds", "3.5",
                               "-o", str(tmp_path / "slow.fobraw")])
    wrote = re.search(r"wrote \S+slow\.fobraw: (\d+) frames of 6 birds in ([\d.]+) s \(([\d.]+) frames/s; "
                      r"the flock measures at 100 Hz\)", err)
    assert wrote, err
    assert 40 <= float(wrote[3]) <= 60  # 50 by the line model above, ±10 for the pty's timing
    warning = next(line for line in err.splitlines() if "frames/s arrive" in line)
    assert "slower than --baud says" in warning and "--baud matching the unit's DIP switches" in warning
    assert "--per-port" in warning and "or lower" in warning
    # The compact format is a fix only if the line, as measured, carries it (6 x 15 B at 100 Hz = 9,000 B/s).
    # An idle pty delivers ~50 frames/s of 6 x 25 B: 7,500 B/s, more than 57600 baud's 5,760, so the line is
    # a 115200 one and the format fits. On a machine at a load of 8-10 the rate window once saw 34.7
    # frames/s: a 57600 line as far as the driver can tell, and then only --rate fits.
    delivered = float(re.search(r"delivers only (\d+) B/s", warning)[1])
    if delivered > 57600 / 10:
        assert "--format position_quaternion" in warning, warning


def test_record_that_fits_its_line_gets_the_asked_rate_and_no_warning(tmp_path, capsys):
    # 6 birds × 15 B (position/quaternion, group mode) at 60 Hz = 5,400 B/s on a 115200 line.
    with PtyTracker(SmoothSource(6), birds=6, baud=115200, rate_hz=100.0) as trk:
        err = _record(capsys, ["--port", trk.device, "--birds", "6", "--rate", "60", "--format",
                               "position_quaternion", "--seconds", "3", "-o", str(tmp_path / "ok.fobraw")])
    rate = float(re.search(r"\(([\d.]+) frames/s; the flock measures at 60 Hz\)", err)[1])
    assert rate == pytest.approx(60, rel=0.05)  # the set rate, within the pty's timing jitter
    assert "frames/s arrive" not in err and "warning" not in err


def test_a_failed_record_leaves_no_stub_and_keeps_an_earlier_file(tmp_path, capsys):
    # Tried: recording over an earlier take from a serial port nobody answers on.
    master, slave = os.openpty()
    out = tmp_path / "take.fobraw"
    out.write_bytes(b"an earlier recording")
    try:
        assert main(["record", "--port", os.ttyname(slave), "--birds", "2", "-o", str(out), "--seconds", "1"]) == 2
    finally:
        os.close(master)
        os.close(slave)
    err = capsys.readouterr().err
    assert "no answer from the flock" in err and err.count("\n") == 1
    assert out.read_bytes() == b"an earlier recording"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["take.fobraw"]  # no .part left either
